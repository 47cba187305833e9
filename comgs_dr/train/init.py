"""Initial surfels for reconstruction step 1: from points, a visual hull, a box/sphere or a PLY."""
from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from comgs_dr.data.types import project
from comgs_dr.surfels.from_mesh import frame_to_quat
from comgs_dr.surfels.kernel import SH_C0
from comgs_dr.surfels.params import SurfelParams


def random_quaternions(n: int, rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


def nn_scale(points: np.ndarray, k: int = 3) -> np.ndarray:
    """3DGS scale init: RMS distance to the k nearest neighbours ([N])."""
    d, _ = cKDTree(points).query(points, k=k + 1)
    s = np.sqrt(np.mean(d[:, 1:] ** 2, axis=1))
    return np.maximum(s, 1e-7).astype(np.float32)


def pca_normal_quaternions(points: np.ndarray, k: int = 16, center=None) -> np.ndarray:
    """[N, 4] w-first quaternions whose surfel normal is the local PCA normal of ``points``
    (smallest-eigenvalue axis of the k nearest neighbours), oriented away from ``center``
    (default: the centroid). For a surface shell such as the visual hull's, this starts
    every surfel tangent to the surface instead of at a random orientation."""
    pts = np.asarray(points, np.float64)
    k = int(min(k, len(pts)))
    _, nb = cKDTree(pts).query(pts, k=k)
    q = pts[nb] - pts[nb].mean(1, keepdims=True)                       # [N, k, 3]
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))          # ascending eigenvalues
    n = vecs[:, :, 0]
    c = pts.mean(0) if center is None else np.asarray(center, np.float64)
    n *= np.where(((pts - c) * n).sum(1, keepdims=True) < 0, -1.0, 1.0)
    t = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    return frame_to_quat(np.stack([t, b, n], -1)).astype(np.float32)


def surfels_from_points(points: np.ndarray, colors: np.ndarray | None, rng: np.random.Generator,
                        sh_degree: int = 0, opacity: float = 0.1,
                        quats: np.ndarray | None = None) -> SurfelParams:
    """NN-based sizes, colour from ``colors`` (display values in [0,1]) or grey; random
    orientations unless ``quats`` [N, 4] are given."""
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4 or not np.all(np.isfinite(pts)):
        raise ValueError(f"surfels_from_points: need ≥ 4 finite points [N, 3], got {pts.shape}")
    n = len(pts)
    s = nn_scale(pts)
    k = (sh_degree + 1) ** 2
    sh = np.zeros((n, k, 3), np.float32)
    if colors is not None:
        sh[:, 0] = (np.clip(np.asarray(colors, np.float32), 0, 1) - 0.5) / SH_C0
    return SurfelParams.from_numpy(
        means=pts, quats=random_quaternions(n, rng) if quats is None else quats,
        log_scales=np.log(np.c_[s, s]),
        opacity_logit=np.full(n, np.log(opacity / (1 - opacity)), np.float32), sh=sh)


def visual_hull_points(views, n: int, center: np.ndarray, radius: float, rng: np.random.Generator,
                       min_fraction: float = 0.95, max_tries: int = 60,
                       shell_px: float | None = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Space carving: uniform points in the bounding sphere kept where at least half of the
    views see them and they project inside the masks of ≥ ``min_fraction`` of those views;
    colour from one such view. With ``shell_px``, only points within that many pixels of
    a mask boundary in some view are kept: the hull's surface shell, where the object's
    surface is (interior points would be hidden surfels that only slow training).

    Returns (points [M, 3], colours [M, 3]); M ≤ n.
    """
    inner = None
    if shell_px is not None:
        inner = [None if v.mask is None else distance_transform_edt(v.mask > 0.5) for v in views]
    keep_p, keep_c = [], []
    total = 0
    box = None
    for _ in range(max_tries):
        if box is None:                           # first pass: the whole bounding sphere
            cand = random_sphere_points(4 * n, center, radius, rng)
        else:                                     # then the (10 % padded) box of what survived
            cand = rng.uniform(box[0], box[1], (4 * n, 3)).astype(np.float32)
        inside = np.zeros(len(cand), np.int32)
        seen = np.zeros(len(cand), np.int32)
        color = np.full((len(cand), 3), 0.5, np.float32)
        depth_px = np.full(len(cand), np.inf)
        for j, v in enumerate(views):
            px, py, ok = project(v.camera, cand)
            if v.mask is None:
                continue
            h, w = v.mask.shape
            xi = np.clip(px.astype(int), 0, w - 1)
            yi = np.clip(py.astype(int), 0, h - 1)
            m = ok & (v.mask[yi, xi] > 0.5)
            seen += ok
            inside += m
            color[m] = v.image[yi[m], xi[m]]
            if inner is not None and inner[j] is not None:
                depth_px = np.where(ok, np.minimum(depth_px, inner[j][yi, xi]), depth_px)
        # Seen by at least half of the views: a point just in front of one camera lands
        # inside that camera's mask but is a floater, not part of the object.
        good = (seen >= max(1, 0.5 * len(views))) & (inside >= min_fraction * seen)
        if inner is not None:
            good &= depth_px <= shell_px
        keep_p.append(cand[good])
        keep_c.append(color[good])
        total += int(good.sum())
        if total >= n:
            break
        if total >= 32:
            allp = np.concatenate(keep_p)
            lo, hi = allp.min(0), allp.max(0)
            box = (lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo))
    pts = np.concatenate(keep_p)[:n]
    cols = np.concatenate(keep_c)[:n]
    if len(pts) < 4:
        raise ValueError("visual hull initialisation found no points inside the masks; check the "
                         "masks and cameras, or initialise from random points")
    return pts.astype(np.float32), cols




def frustum_points(views, n: int, center, radius: float, rng: np.random.Generator,
                   min_seen: float = 0.5, max_tries: int = 40) -> np.ndarray:
    """Uniform points in the bounding sphere that at least ``min_seen`` of the views see
    (the common view frustum): a random initialisation without masks or SfM points.

    The bounding sphere encloses the cameras; filling all of it puts most surfels beside or
    right in front of the cameras, where they occlude every view they are in and get pruned
    only slowly (measured on the procedural scene: a grey blob, 14.7 dB after 750 iterations).
    Returns [M, 3] float32 with M = n, or fewer if the frustum is tiny (at least 4, else an error).
    """
    keep, total = [], 0
    for _ in range(max_tries):
        cand = random_sphere_points(4 * n, center, radius, rng)
        seen = np.zeros(len(cand), np.int32)
        for v in views:
            seen += project(v.camera, cand)[2]
        good = cand[seen >= max(1, min_seen * len(views))]
        keep.append(good)
        total += len(good)
        if total >= n:
            break
    pts = np.concatenate(keep)[:n]
    if len(pts) < 4:
        raise ValueError(f"random initialisation: no point of the bounding sphere is seen by "
                         f"{min_seen:.0%} of the {len(views)} training views; check the camera poses")
    return pts.astype(np.float32)


def random_sphere_points(n: int, center, radius: float, rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return (np.asarray(center) + d * radius * rng.uniform(0, 1, (n, 1)) ** (1 / 3)).astype(np.float32)
