"""Datasets for reconstruction step 1: NeRF-synthetic, COLMAP and LLFF folders.

Every loader returns a :class:`SceneData` of :class:`View` s whose :class:`Camera` s are in
Mitsuba's convention (camera-to-world ``to_world``; camera space +X left, +Y up,
+Z forward; ``camera.sensor_dict()`` gives a ``perspective`` sensor with a box filter and
the principal point). World up is +Z: NeRF-synthetic is Z-up already; COLMAP/LLFF worlds
are rotated with ``up="auto"`` (default). Conversions:

==============  =========================================  ===================================
format          stored pose                                Mitsuba ``to_world``
==============  =========================================  ===================================
NeRF-synthetic  camera-to-world, OpenGL (+X right, +Y up,  ``M @ diag(-1, 1, -1, 1)``
                looks down -Z)
COLMAP          world-to-camera, OpenCV (+X right, +Y      ``inv(M) @ diag(-1, -1, 1, 1)``
                down, +Z forward)
LLFF            camera-to-world, columns [down, right,     ``M @ MITSUBA_FROM_LLFF``
                back]
==============  =========================================  ===================================

Images keep their stored (display sRGB) values as float32 in [0, 1]; RGBA images are
composited onto the background (``colour = rgb a + bg (1 - a)``, ``mask = a``).
``resolution_scale`` k crops to a multiple of k and area-averages k x k blocks; image,
mask and intrinsics are scaled together. Problems with the data raise
:class:`DatasetError` (a ValueError) naming the offending file.
"""
from __future__ import annotations

from pathlib import Path

from comgs_dr.data.colmap import load_colmap
from comgs_dr.data.llff import load_llff
from comgs_dr.data.nerf import load_nerf_synthetic
from comgs_dr.data.types import (
    MITSUBA_FROM_LLFF,
    MITSUBA_FROM_OPENCV,
    MITSUBA_FROM_OPENGL,
    Camera,
    DatasetError,
    SceneData,
    View,
    compute_bounds,
)

__all__ = ["Camera", "View", "SceneData", "DatasetError", "load_dataset", "camera_fingerprint",
           "load_nerf_synthetic", "load_colmap", "load_llff", "detect_format",
           "compute_bounds", "MITSUBA_FROM_OPENGL", "MITSUBA_FROM_OPENCV", "MITSUBA_FROM_LLFF"]

_LOADERS = {"nerf_synthetic": load_nerf_synthetic, "colmap": load_colmap, "llff": load_llff}


def detect_format(path) -> str:
    """"nerf_synthetic" (transforms_train.json), "colmap" (sparse/0 or sparse with a model;
    preferred over LLFF when both exist) or "llff" (poses_bounds.npy)."""
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    if (root / "transforms_train.json").is_file():
        return "nerf_synthetic"
    for d in (root / "sparse" / "0", root / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return "colmap"
    if (root / "poses_bounds.npy").is_file():
        return "llff"
    raise DatasetError(f"{root}: unknown dataset layout (looked for transforms_train.json, "
                       "sparse[/0]/cameras.{bin,txt}, poses_bounds.npy)")


def load_dataset(path, format: str = "auto", **kw) -> SceneData:
    """Load a dataset folder, detecting its format (or forcing ``format``); ``kw`` go to
    the loader (e.g. ``resolution_scale``, ``max_views``, ``white_background``, ``up``;
    ``pixels=False``: cameras only, each image's size read from its header).
    A path to a transforms json or to ``poses_bounds.npy`` means its folder."""
    root = Path(path)
    if root.is_file():
        root = root.parent
    fmt = detect_format(root) if format == "auto" else format
    if fmt not in _LOADERS:
        raise ValueError(f"load_dataset: format must be 'auto' or one of "
                         f"{', '.join(_LOADERS)}, got {format!r}")
    return _LOADERS[fmt](root, **kw)


_CAMERA_FILES = ("transforms_*.json", "sparse/cameras.*", "sparse/images.*",
                 "sparse/0/cameras.*", "sparse/0/images.*", "poses_bounds.npy")


def camera_fingerprint(path) -> str | None:
    """SHA-256 of a dataset folder's camera files (transforms files, the COLMAP model's
    cameras/images, ``poses_bounds.npy``: their names and bytes), or None when the folder
    holds none. A run records it: re-running SfM into the dataset's folder moves every
    camera to a new frame, and a run trained on the old one would render misplaced."""
    import hashlib
    root = Path(path)
    if root.is_file():
        root = root.parent
    files = sorted({f for pat in _CAMERA_FILES for f in root.glob(pat) if f.is_file()})
    if not files:
        return None
    h = hashlib.sha256()
    for f in files:
        h.update(f.relative_to(root).as_posix().encode() + b"\0")
        h.update(f.read_bytes())
    return h.hexdigest()
