"""Surfel data model, I/O, sampling from meshes, and the ``surfels`` shape."""
from comgs_dr.surfels.io import SurfelFileError, load_ply, load_splat, save_ply
from comgs_dr.surfels.params import (SurfelParams, base_colour, sh_coeff_count,
                                     sh_degree_from_count, sh_from_base_colour)
from comgs_dr.surfels.shape import SurfelShapeBase, shape_class

# Last on purpose: the function shares its submodule's name; binding it after the submodule
# is loaded keeps ``surfels.from_mesh`` the function whatever is imported later.
from comgs_dr.surfels.from_mesh import from_mesh  # noqa: E402  isort: skip

__all__ = ["SurfelParams", "SurfelShapeBase", "shape_class", "load_ply", "save_ply", "load_splat",
           "SurfelFileError", "from_mesh", "sh_coeff_count", "sh_degree_from_count",
           "base_colour", "sh_from_base_colour"]
