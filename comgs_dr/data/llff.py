"""LLFF datasets: ``poses_bounds.npy`` + ``images/`` (or ``images_<k>/``).

``poses_bounds.npy`` is [N, 17]: per image (sorted by file name) a 3x5 matrix
[R | t | hwf] flattened row-major, then (near, far). R's columns are the camera's
[down, right, back] axes in world space and t its centre: a camera-to-world in LLFF's
axis order. Mitsuba's camera axes are left = -right, up = -down, forward = -back, so

    to_world = [R | t] @ MITSUBA_FROM_LLFF,  MITSUBA_FROM_LLFF = [[0,-1,0],[-1,0,0],[0,0,-1]]

(a proper rotation; the same as OpenCV [right, down, forward] = [col1, col0, -col2]
followed by diag(-1, -1, 1)). hwf = (height, width, focal) in pixels of the images the
poses were computed on; the focal is rescaled to the files actually read and the
principal point is the image centre. The world is COLMAP's, so ``up`` works as in
:func:`load_colmap`. No recentring or rescaling is applied (unlike NeRF's loader).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from comgs_dr.data.images import check_scale, list_images, load_view, scaled_intrinsics
from comgs_dr.data.types import (
    MITSUBA_FROM_LLFF,
    DatasetError,
    SceneData,
    aligned_split,
    rigid_pose,
    subsample,
)


def load_llff(root, resolution_scale: int = 1, test_every: int = 8, images: str | None = None,
              up: str = "auto", max_views: int | None = None,
              white_background: bool = False) -> SceneData:
    """Load an LLFF folder; every ``test_every``-th image (sorted by name) is test.

    ``images``: image folder under ``root`` (None: ``images`` if present, else the
    ``images_<k>`` with the smallest k). ``up``: "auto" rotates the world so the mean
    camera up is +Z, "none" keeps COLMAP's frame. Images with alpha are composited onto
    white/black (``white_background``), alpha = mask. Raises DatasetError naming the path.
    """
    root, k = Path(root), check_scale(resolution_scale)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    pb_path = root / "poses_bounds.npy"
    if not pb_path.is_file():
        raise DatasetError(f"{pb_path}: file not found")
    try:
        pb = np.load(pb_path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise DatasetError(f"{pb_path}: unreadable ({e})") from None
    if pb.ndim != 2 or pb.shape[1] != 17 or len(pb) == 0:
        raise DatasetError(f"{pb_path}: expected an [N, 17] array with N >= 1, got {pb.shape}")
    folder = _image_folder(root, images)
    files = list_images(folder)
    if len(files) != len(pb):
        raise DatasetError(f"{folder}: {len(files)} images but {pb_path} has {len(pb)} poses")

    poses = pb[:, :15].reshape(-1, 3, 5).astype(np.float64)     # [N, 3, 5]
    frames = []
    for i, f in enumerate(files):
        where = f"{pb_path} pose {i} ({f.name})"
        h, w, focal = poses[i, :, 4]
        if not (np.isfinite([h, w, focal]).all() and min(h, w, focal) > 0):
            raise DatasetError(f"{where}: invalid hwf {poses[i, :, 4].tolist()}")
        frames.append({"name": f.stem, "path": f,
                       "to_world": rigid_pose(poses[i, :, :4], where) @ MITSUBA_FROM_LLFF,
                       "intrinsics": scaled_intrinsics(focal, focal, w / 2, h / 2, w, h, where)})
    rot, tr, te = aligned_split(frames, up, str(pb_path), test_every)
    bg = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    load = lambda idx: [load_view(f["name"], f["path"], f["to_world"], f["intrinsics"], k, bg)
                        for f in subsample([frames[i] for i in idx], max_views)]
    near_far = {f["name"]: tuple(map(float, b)) for f, b in zip(frames, pb[:, 15:])}
    return SceneData(train=load(tr), test=load(te), world_from_source=rot,
                     white_background=bool(white_background),
                     source=f"llff:{root} ({folder.name}, test every {test_every}, up={up}, "
                            f"scale 1/{k})",
                     meta={"format": "llff", "resolution_scale": k, "near_far": near_far})


def _image_folder(root: Path, images: str | None) -> Path:
    if images is not None:
        folder = root / images
        if not folder.is_dir():
            raise DatasetError(f"{folder}: image folder not found")
        return folder
    if (root / "images").is_dir():
        return root / "images"
    sub = sorted((int(m.group(1)), p) for p in root.glob("images_*")
                 if p.is_dir() and (m := re.fullmatch(r"images_(\d+)", p.name)))
    if not sub:
        raise DatasetError(f"{root / 'images'}: image folder not found (nor images_<k>)")
    return sub[0][1]
