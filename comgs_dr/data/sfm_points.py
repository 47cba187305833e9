"""SfM-like sparse points for synthetic datasets (``points3d.ply``, as COLMAP would give).

A real scene capture comes with COLMAP's sparse cloud: surface points triangulated from at
least two views, with colour and a little noise. Synthetic scene datasets get the same from
the ground-truth mesh: area-uniform surface samples that at least ``min_views`` training
cameras see unoccluded, coloured by a training image, jittered by ``noise`` × the scene radius.
The NeRF-synthetic loader (``data.nerf``) reads the file when it is present.
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import mitsuba as mi
import numpy as np

from comgs_dr.core.colorspace import srgb_encode
from comgs_dr.core.hostarray import to_jit
from comgs_dr.data.types import project


def sample_visible_points(scene, cameras: list[dict], images: list[np.ndarray], fov_deg: float,
                          n: int, rng: np.random.Generator, min_views: int = 2,
                          noise: float = 0.002, radius: float = 1.0, max_tries: int = 20
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(points [M, 3] float32, colours [M, 3] uint8), M ≤ n, from the shapes of Mitsuba
    ``scene`` seen by ≥ ``min_views`` of ``cameras`` ({"to_world_mitsuba": [4, 4]}) with
    ``images`` [H, W, ≥3] linear RGB(A) renders of those cameras (colour: sRGB of the first
    view that sees the point). Raises ValueError if no point is seen often enough."""

    # sorted by id: a scene's children load in parallel, in no fixed order
    shapes = sorted((s for s in scene.shapes() if not s.is_emitter()), key=lambda s: s.id())
    area = np.array([float(np.asarray(s.surface_area()).ravel()[0]) for s in shapes])
    if not shapes or area.sum() <= 0:
        raise ValueError("sample_visible_points: the scene has no surface to sample")
    h, w = images[0].shape[:2]
    cams = [SimpleNamespace(to_world=np.asarray(c["to_world_mitsuba"], float), width=w, height=h,
                            fov_x_deg=fov_deg) for c in cameras]
    pts_all, col_all = [], []
    for _ in range(max_tries):
        m = 4 * n
        which = rng.choice(len(shapes), m, p=area / area.sum())
        p = np.zeros((m, 3))
        nrm = np.zeros((m, 3))
        for k, s in enumerate(shapes):
            sel = np.nonzero(which == k)[0]
            if not len(sel):
                continue
            ps = s.sample_position(0.0, to_jit(mi.Point2f, rng.random((2, len(sel)))))
            p[sel] = np.asarray(ps.p).T if np.asarray(ps.p).ndim == 2 else np.asarray(ps.p)
            nrm[sel] = np.asarray(ps.n).T if np.asarray(ps.n).ndim == 2 else np.asarray(ps.n)
        seen = np.zeros(m, np.int32)
        color = np.full((m, 3), np.nan)
        for cam, img in zip(cams, images):
            x, y, ok = project(cam, p)
            o = cam.to_world[:3, 3]
            d = o[None] - p
            dist = np.linalg.norm(d, axis=1)
            d /= np.maximum(dist, 1e-12)[:, None]
            front = (d * nrm).sum(1)
            origin = p + np.sign(front)[:, None] * 1e-4 * radius * nrm
            ray = mi.Ray3f(to_jit(mi.Point3f, origin.T), to_jit(mi.Vector3f, d.T))
            ray.maxt = to_jit(mi.Float, dist * (1 - 1e-4))
            vis = ok & ~np.asarray(scene.ray_test(ray), bool)
            seen += vis
            first = vis & np.isnan(color[:, 0])
            xi = np.clip(x[first].astype(int), 0, w - 1)
            yi = np.clip(y[first].astype(int), 0, h - 1)
            color[first] = img[yi, xi, :3]
        good = seen >= min_views
        pts_all.append(p[good])
        col_all.append(color[good])
        if sum(len(a) for a in pts_all) >= n:
            break
    pts = np.concatenate(pts_all)[:n]
    col = np.concatenate(col_all)[:n]
    if not len(pts):
        raise ValueError(f"sample_visible_points: no surface point is seen by {min_views} cameras")
    pts = pts + rng.normal(0, noise * radius, pts.shape)
    srgb = srgb_encode(col)
    return pts.astype(np.float32), np.clip(np.round(srgb * 255), 0, 255).astype(np.uint8)


def write_points_ply(path, points: np.ndarray, colors: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY with x y z float and optional red green blue uchar."""
    path = Path(path)
    pts = np.asarray(points, np.float32)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.zeros(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts.T
    if colors is not None:
        c = np.asarray(colors, np.uint8)
        rec["red"], rec["green"], rec["blue"] = c.T
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {n}\n" for n, t in fields)
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n{props}end_header\n"
    path.write_bytes(head.encode() + rec.tobytes())
    return path
