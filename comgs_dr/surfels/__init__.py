"""Surfel data model, I/O, sampling from meshes, and the ``surfels`` shape."""
from .params import SurfelParams, sh_coeff_count, sh_degree_from_count  # noqa: F401


def __getattr__(name):  # lazy: io/from_mesh pull in plyfile/trimesh
    if name in ("load_ply", "save_ply"):
        from . import io
        return getattr(io, name)
    if name == "from_mesh":
        from .from_mesh import from_mesh
        return from_mesh
    if name == "SurfelShape":
        from .shape import SurfelShape
        return SurfelShape
    raise AttributeError(name)


__all__ = ["SurfelParams", "SurfelShape", "load_ply", "save_ply", "from_mesh",
           "sh_coeff_count", "sh_degree_from_count"]
