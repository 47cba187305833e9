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
    compute_bounds,
    MITSUBA_FROM_LLFF,
    DatasetError,
    SceneData,
    aligned_split,
    rigid_pose,
    subsample,
)


def load_llff(root, resolution_scale: int = 1, test_every: int = 8, images: str | None = None,
              up: str = "auto", max_views: int | None = None,
              white_background: bool = False, pixels: bool = True) -> SceneData:
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
    except Exception as e:  # noqa: BLE001 - a damaged .npy header raises SyntaxError, EOFError, ...
        raise DatasetError(f"{pb_path}: not a readable .npy array ({type(e).__name__}: {e})") \
            from None
    if not isinstance(pb, np.ndarray) or pb.ndim != 2 or pb.shape[1] != 17 or len(pb) == 0:
        raise DatasetError(f"{pb_path}: expected an [N, 17] array with N >= 1, got "
                           f"{getattr(pb, 'shape', type(pb).__name__)}")
    if pb.dtype.kind not in "fiu":
        raise DatasetError(f"{pb_path}: expected real numbers, got dtype {pb.dtype}")
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
    load = lambda idx: [load_view(f["name"], f["path"], f["to_world"], f["intrinsics"], k, bg,
                                  pixels=pixels)
                        for f in subsample([frames[i] for i in idx], max_views)]
    near_far = {f["name"]: tuple(map(float, b)) for f, b in zip(frames, pb[:, 15:])}
    train, test = load(tr), load(te)
    return SceneData(train=train, test=test, world_from_source=rot,
                     white_background=bool(white_background),
                     bounds=llff_bounds([v.camera for v in train + test],
                                        [near_far[v.name] for v in train + test]),
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


def llff_bounds(cameras, near_far, forward_cos: float = 0.9) -> tuple[np.ndarray, float]:
    """:attr:`SceneData.bounds` of an LLFF capture: (camera centroid, extent).

    :func:`compute_bounds` (3DGS's "cameras extent", the camera centres' sphere x1.1) is
    the scene's size for captures that surround it. A forward-facing capture's cameras
    sit in a small patch (a hand-held baseline) far smaller than the depth they look
    into, and step 1 scales the position learning rate and the largest surfel σ
    (``max_scale_frac`` x extent) by the extent: with the camera sphere, σ stays below a
    pixel at the far content and positions barely move. So for a forward-facing capture
    (the mean of the unit viewing directions is at least ``forward_cos`` long; 0.9: all
    views look within ~25° of one direction) with near/far bounds, the extent is the
    larger of that camera radius and the median over views of sqrt(near · far), the
    typical content depth (the geometric mean: depths span ratios, and the disparity
    range's midpoint is close to it). Captures that surround the scene (e.g. mip-NeRF
    360's poses_bounds.npy) keep the camera sphere, as 3DGS.
    ``near_far`` [N, 2] z-depths, one pair per camera (None or empty: camera sphere).

    Measured on the synthetic forward-facing capture (``comgs_dr.data.llff_synthetic``,
    near 2.1, far 9.3, camera radius 0.64; 17 views at 100x75, 1500 its, plane-sweep
    init, ``--lambda-d2n 0``), test PSNR peak / final: camera radius 8.5 dB at 300 its;
    far bound (9.3) 22.6 / 20.9 dB, 15 % of the surfels at the σ cap; sqrt(near far)
    (4.5) 23.4 / 22.8 dB.
    """
    cameras = list(cameras)
    center, radius = compute_bounds(cameras)
    nf = None if near_far is None else np.asarray(near_far, np.float64).reshape(-1, 2)
    if not cameras or nf is None or len(nf) != len(cameras) \
            or not (np.isfinite(nf).all() and (nf > 0).all()):
        return center, radius
    fwd = np.array([np.asarray(c.to_world, np.float64)[:3, 2] for c in cameras])
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    if np.linalg.norm(fwd.mean(0)) >= forward_cos:
        radius = max(radius, float(np.median(np.sqrt(nf[:, 0] * nf[:, 1]))))
    return center, radius


def view_near_far(data: SceneData, views=None) -> np.ndarray | None:
    """[N, 2] (near, far) z-depths of ``views`` (default ``data.train``) from the poses'
    bounds (``data.meta["near_far"]``, kept by :func:`load_llff`), or None when the
    dataset has none (other formats) or any view lacks a valid pair."""
    table = (data.meta or {}).get("near_far")
    views = data.train if views is None else views
    if not table or not views:
        return None
    try:
        nf = np.array([table[v.name] for v in views], np.float64).reshape(-1, 2)
    except KeyError:
        return None
    ok = np.isfinite(nf).all() and (nf[:, 0] > 0).all() and (nf[:, 1] > nf[:, 0]).all()
    return nf if ok else None
