"""NeRF-synthetic (Blender) datasets: ``transforms_{train,test}.json`` + RGBA PNGs.

The scenes are Z-up already, so the world frame is kept. ``transform_matrix`` is an
OpenGL camera-to-world (+X right, +Y up, looks down -Z); Mitsuba's ``to_world`` is
``transform_matrix @ diag(-1, 1, -1, 1)``. Intrinsics: ``camera_angle_x`` (radians,
horizontal FOV, principal point at the image centre), or the instant-ngp/nerfstudio keys
``fl_x fl_y cx cy w h`` (pixels for a w x h image), top-level or per frame. Non-zero
distortion keys (``k1 k2 k3 k4 p1 p2``) are refused.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import plyfile

from comgs_dr.data.images import (
    IMAGE_EXTENSIONS,
    check_scale,
    load_view,
    missing_error,
    resolve_image,
    scaled_intrinsics,
)
from comgs_dr.data.types import (
    MITSUBA_FROM_OPENGL,
    DatasetError,
    SceneData,
    holdout,
    rigid_pose,
    subsample,
)

_INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def load_nerf_synthetic(root, white_background: bool = False, resolution_scale: int = 1,
                        max_views: int | None = None, test_every: int = 8,
                        pixels: bool = True) -> SceneData:
    """Load a NeRF-synthetic folder.

    Without ``transforms_test.json`` every ``test_every``-th train frame (0, 8, 16, ...) is
    held out as test. RGBA images are composited onto white/black (``white_background``),
    the alpha becoming the mask. ``max_views`` caps each split (evenly spaced). A
    ``points3d.ply`` beside the JSON files (x, y, z and optional red/green/blue; world frame
    of the transforms, as 3DGS reads it) gives the initial points.
    Raises DatasetError naming the offending file.
    """
    root, k = Path(root), check_scale(resolution_scale)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    train = _frames(root / "transforms_train.json", root)
    test_json = root / "transforms_test.json"
    if test_json.is_file():
        test = _frames(test_json, root)
        split = "transforms_test.json"
    else:
        tr, te = holdout(len(train), test_every)
        train, test = [train[i] for i in tr], [train[i] for i in te]
        split = f"every {test_every}th train frame held out"
        if not train:
            raise DatasetError(f"{root / 'transforms_train.json'}: no training frames left "
                               f"after holding out every {test_every}th frame")
    bg = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    load = lambda fr: [load_view(f["name"], f["path"], f["to_world"], f["intrinsics"], k, bg,
                                 pixels=pixels)
                       for f in subsample(fr, max_views)]
    points, colors = read_points_ply(root / "points3d.ply") if (root / "points3d.ply").is_file() \
        else (None, None)
    return SceneData(train=load(train), test=load(test), white_background=bool(white_background),
                     points=points, colors=colors,
                     source=f"nerf_synthetic:{root} (test: {split}, scale 1/{k})",
                     meta={"format": "nerf_synthetic", "resolution_scale": k})


def read_points_ply(path: Path):
    """(points [P, 3] float32, colours [P, 3] float32 in [0, 1] or None) of a point PLY.
    DatasetError naming the file if it is unreadable, lacks x/y/z or has non-finite points."""
    try:
        v = plyfile.PlyData.read(str(path))["vertex"].data
        pts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32)
    except Exception as exc:   # plyfile raises several types on bad files
        raise DatasetError(f"{path}: not a readable point PLY with x/y/z ({exc})") from exc
    if len(pts) < 4 or not np.isfinite(pts).all():
        raise DatasetError(f"{path}: need >= 4 finite points, got {len(pts)} "
                           f"({int((~np.isfinite(pts).all(1)).sum())} non-finite)")
    names = v.dtype.names
    colors = None
    if all(c in names for c in ("red", "green", "blue")):
        colors = np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.float32)
        colors /= 255.0 if v["red"].dtype == np.uint8 else max(1.0, float(colors.max()))
    return pts, colors


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        d = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: invalid JSON ({e})") from None
    if not isinstance(d, dict):
        raise DatasetError(f"{path}: expected a JSON object with 'frames'")
    return d


def _frames(path: Path, root: Path) -> list[dict]:
    """Validated frames of one transforms json: name, path, to_world, intrinsics."""
    d = _read_json(path)
    frames = d.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: no frames (empty split)")
    top = {key: d[key] for key in _INTRINSIC_KEYS + _DISTORTION_KEYS if key in d}
    out, missing = [], []
    for i, fr in enumerate(frames):
        fp = fr.get("file_path") if isinstance(fr, dict) else None
        where = f"{path} frame {i} ({fp})"
        if not isinstance(fp, str):
            raise DatasetError(f"{path} frame {i}: missing 'file_path'")
        if "transform_matrix" not in fr:
            raise DatasetError(f"{where}: missing 'transform_matrix'")
        to_world = rigid_pose(fr["transform_matrix"], where) @ MITSUBA_FROM_OPENGL
        img = resolve_image(root, fp)
        if img is None:
            missing.append(fp)
            continue
        cam = {**top, **{key: fr[key] for key in _INTRINSIC_KEYS + _DISTORTION_KEYS if key in fr}}
        name = fp[2:] if fp.startswith("./") else fp
        if Path(name).suffix.lower() in IMAGE_EXTENSIONS:
            name = str(Path(name).with_suffix(""))
        out.append({"name": name, "path": img, "to_world": to_world,
                    "intrinsics": _intrinsics(cam, where)})
    if missing:
        raise missing_error(f"image files (relative to {root})", path, missing, len(frames))
    return out


def _intrinsics(c: dict, where: str):
    """Callable (w, h) -> pixel (fx, fy, cx, cy) for the frame's keys."""
    try:
        c = {key: float(v) for key, v in c.items()}
    except (TypeError, ValueError) as e:
        raise DatasetError(f"{where}: non-numeric camera intrinsics ({e})") from None
    bad = [key for key, v in c.items() if not math.isfinite(v)]
    if bad:
        raise DatasetError(f"{where}: non-finite camera intrinsics {bad}")
    if any(c.get(key, 1.0) < 1.0 for key in ("w", "h")):
        raise DatasetError(f"{where}: image size w={c.get('w')}, h={c.get('h')} must be >= 1")
    if any(abs(c.get(key, 0.0)) > 1e-6 for key in _DISTORTION_KEYS):
        raise DatasetError(f"{where}: distorted camera (non-zero {'/'.join(_DISTORTION_KEYS)});"
                           " undistort the images first (e.g. colmap image_undistorter)")
    if "fl_x" not in c and "camera_angle_x" not in c:
        raise DatasetError(f"{where}: needs 'camera_angle_x' or 'fl_x'")
    for key in ("camera_angle_x", "camera_angle_y"):
        if key in c and not 0.0 < c[key] < math.pi:
            raise DatasetError(f"{where}: {key}={c[key]} is not in (0, pi)")

    def at(w0: int, h0: int):
        w, h = (c["w"], c["h"]) if "w" in c and "h" in c else (w0, h0)
        fx = c["fl_x"] if "fl_x" in c else 0.5 * w / math.tan(c["camera_angle_x"] / 2)
        fy = c.get("fl_y", 0.5 * h / math.tan(c["camera_angle_y"] / 2)
                   if "camera_angle_y" in c else fx)
        return scaled_intrinsics(fx, fy, c.get("cx", w / 2), c.get("cy", h / 2), w, h,
                                 where)(w0, h0)
    return at



def split_frames(root, split: str) -> list[dict]:
    """The raw frames of ``root/transforms_<split>.json`` (with the ground-truth paths that
    ``comgs make-dataset`` records: ``normal_path``, ``depth_path``, ``albedo_path``); [] if
    the file is absent."""
    path = Path(root) / f"transforms_{split}.json"
    return _read_json(path).get("frames", []) if path.exists() else []
