"""Surfel data model, I/O, sampling from meshes, and the ``surfels`` shape."""
from .params import SurfelParams, sh_coeff_count, sh_degree_from_count  # noqa: F401
# Eager on purpose: the function shares the submodule's name, and binding it here (the
# module imports trimesh lazily, so this is cheap) keeps `surfels.from_mesh` the function
# whatever is imported later.
from .from_mesh import from_mesh  # noqa: F401,E402


def __getattr__(name):  # lazy: io pulls in plyfile, shape builds per-variant types
    if name in ("load_ply", "save_ply", "load_splat", "SurfelFileError"):
        from . import io
        return getattr(io, name)
    if name in ("SurfelShapeBase", "shape_class"):
        from . import shape
        return getattr(shape, name)
    raise AttributeError(name)


__all__ = ["SurfelParams", "SurfelShapeBase", "shape_class", "load_ply", "save_ply", "load_splat",
           "SurfelFileError", "from_mesh",
           "sh_coeff_count", "sh_degree_from_count"]
