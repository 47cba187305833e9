"""Automatic placement of SOPs (paper, "Automatic Placement of SOPs").

1. Render geometry buffers (W, unbiased depth D̃, N) of the reconstructed surfels from the
   training cameras and back-project every covered pixel (W ≥ ``min_weight``) to a 3D point
   with its normal.
2. Multi-view depth fusion (in the spirit of Galliani et al. 2015): a point is kept when at
   least ``min_consistent`` *other* views see it — it projects inside their image, their
   depth there agrees within ``depth_tol`` (relative) and their normal within
   ``normal_tol_deg``. Points seen by one view only, floaters and depth-blend artefacts at
   silhouettes drop out.
3. Farthest point sampling (the ``fpsample`` library) picks ``count`` well-spread points.
4. Each probe is offset along its normal by ``offset_frac`` × object size (1 % in sec. 4.1).

The query radius is set from the FPS spacing so that a surface point has ~``neighbours``
probes within it (radius = spacing·sqrt(neighbours/π)·√2, spacing = the smallest FPS
distance; see :func:`place_probes`).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import fpsample
import mitsuba as mi
import numpy as np
from scipy.spatial import cKDTree

from comgs_dr.core.cameras import camera_rays
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.surfels.params import object_bounds
from comgs_dr.surfels.scene import gbuffer_scene

CLIP_FRACS = (1e-4, 1e4)    # sensor clip planes × the scene extent (as data.types.CLIP_FRACS)


@dataclass(frozen=True)
class PlacementConfig:
    count: int = 5000                 # number of probes (sec. 4.1: 5k)
    res: int = 16                     # octahedral texels per side (sec. 4.1: 16²)
    offset_frac: float = 0.01         # offset along the normal, × object size (sec. 4.1: 1 %)
    min_weight: float = 0.5           # pixels with W below this are not surface
    min_consistent: int = 2           # other views that must agree
    depth_tol: float = 0.01           # relative depth agreement
    normal_tol_deg: float = 30.0
    max_views: int = 32               # G-buffers rendered for fusion (evenly spread)
    neighbours: float = 8.0           # target probes within the query radius
    max_hits: int = 32

    def __post_init__(self):
        if self.count < 1 or self.res < 2:
            raise ValueError(f"PlacementConfig: count ≥ 1 and res ≥ 2 required, got "
                             f"{self.count}, {self.res}")
        if self.min_consistent < 0 or self.max_views < 1:
            raise ValueError("PlacementConfig: min_consistent ≥ 0 and max_views ≥ 1 required")


@dataclass
class FusedPoints:
    points: np.ndarray        # [M, 3]
    normals: np.ndarray       # [M, 3]
    per_view: list            # points back-projected per view (before the check)


def render_geometry(params, cameras, max_hits: int = 32) -> list[dict]:
    """Per camera: {'weight' [H,W], 'depth' [H,W] (unbiased), 'normal' [H,W,3],
    'origins'/'dirs' [H,W,3]} from the ``surfel_gbuffer`` integrator. Clip planes scale
    with the surfels and cameras (``clip_planes``: a 1 mm object is not clipped away)."""
    lo, hi = object_bounds(params)
    centres = np.array([c.center for c in cameras]).reshape(-1, 3)
    extent = max(float(np.linalg.norm(hi - lo)),
                 float(np.linalg.norm(centres - (lo + hi) / 2, axis=1).max()), 1e-30)
    sensors = [c.sensor_dict(near_clip=CLIP_FRACS[0] * extent, far_clip=CLIP_FRACS[1] * extent)
               for c in cameras]
    scene = gbuffer_scene({"surfels": params}, sensors, max_hits=max_hits,
                          targets="weight,depth_unbiased,normal")
    integ = scene.integrator()
    out = []
    for i, cam in enumerate(cameras):
        with dr.suspend_grad():
            parts = integ.split(mi.render(scene, sensor=i))
        dirs, origins = camera_rays(scene.sensors()[i])
        out.append({"weight": np.asarray(parts["weight"])[..., 0],
                    "depth": np.asarray(parts["depth_unbiased"])[..., 0],
                    "normal": np.asarray(parts["normal"]),
                    "dirs": np.asarray(dirs), "origins": np.asarray(origins)})
    return out


def fuse_depth(cameras, buffers, cfg: PlacementConfig) -> FusedPoints:
    """Back-project every view and keep multi-view-consistent points (step 2 above)."""
    per_view = []
    for buf in buffers:
        m = (buf["weight"] >= cfg.min_weight) & np.isfinite(buf["depth"]) & (buf["depth"] > 0)
        p = buf["origins"][m] + buf["dirs"][m] * buf["depth"][m][:, None]
        n = buf["normal"][m]
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        per_view.append((p, n))
    cos_tol = np.cos(np.radians(cfg.normal_tol_deg))
    pts, nrm = [], []
    for v, (p, n) in enumerate(per_view):
        if len(p) == 0:
            continue
        votes = np.zeros(len(p), np.int64)
        for u, (cam, buf) in enumerate(zip(cameras, buffers)):
            if u == v:
                continue
            pix, _ = cam.project(p)
            x = np.floor(pix[:, 0]).astype(np.int64)
            y = np.floor(pix[:, 1]).astype(np.int64)
            inside = (x >= 0) & (y >= 0) & (x < cam.width) & (y < cam.height)
            xi, yi = np.clip(x, 0, cam.width - 1), np.clip(y, 0, cam.height - 1)
            o = buf["origins"][yi, xi]
            dist = np.linalg.norm(p - o, axis=1)            # along-ray distance from u's origin
            d_u = buf["depth"][yi, xi]
            ok = inside & (buf["weight"][yi, xi] >= cfg.min_weight)
            ok &= np.abs(d_u - dist) <= cfg.depth_tol * np.maximum(dist, 1e-12)
            ok &= (buf["normal"][yi, xi] * n).sum(1) >= cos_tol * np.linalg.norm(
                buf["normal"][yi, xi], axis=1)
            votes += ok
        keep = votes >= cfg.min_consistent
        pts.append(p[keep])
        nrm.append(n[keep])
    points = np.concatenate(pts) if pts else np.zeros((0, 3))
    normals = np.concatenate(nrm) if nrm else np.zeros((0, 3))
    return FusedPoints(points, normals, per_view)


def farthest_points(points: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Indices of ``count`` farthest-point samples (``fpsample`` library, bucket/KD-line
    variant: exact FPS order up to ties)."""
    n = len(points)
    if count >= n:
        return np.arange(n)
    start = int(np.random.default_rng(seed).integers(n))
    h = min(7, int(np.log2(n)))             # the KD-line height needs 2^h <= n (else it asserts)
    idx = fpsample.bucket_fps_kdline_sampling(np.ascontiguousarray(points, np.float32),
                                              count, h=h, start_idx=start)
    return np.asarray(idx, np.int64)


def probe_spacing(pts: np.ndarray, size: float) -> float:
    """Median nearest-neighbour distance of FPS samples (≈ the covering radius); ``size``
    for a single point."""
    if len(pts) < 2:
        return float(size)
    dist, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(dist[:, 1]))


def query_radius(pts: np.ndarray, neighbours: float, size: float) -> float:
    """Query radius with ~``neighbours`` probes inside: spacing·sqrt(neighbours/π)·√2."""
    spacing = probe_spacing(pts, size)
    return max(spacing * np.sqrt(neighbours / np.pi) * np.sqrt(2.0), 1e-6 * size)


def place_probes(params, cameras, cfg: PlacementConfig = PlacementConfig(),
                 object_size: float | None = None, seed: int = 0) -> ProbeSet:
    """Probe positions/normals for a reconstructed object (textures not yet baked).

    ``object_size``: the offset reference (default: bounding-box diagonal of the fused
    points). Raises ValueError when fusion leaves no point (e.g. wrong cameras).
    """
    if len(cameras) == 0:
        raise ValueError("place_probes: no cameras given")
    sel = np.unique(np.linspace(0, len(cameras) - 1, min(cfg.max_views, len(cameras)))
                    .round().astype(int))
    cams = [cameras[i] for i in sel]
    buffers = render_geometry(params, cams, cfg.max_hits)
    need = min(cfg.min_consistent, len(cams) - 1)
    fused = fuse_depth(cams, buffers, cfg if need == cfg.min_consistent
                       else PlacementConfig(**{**cfg.__dict__, "min_consistent": need}))
    if len(fused.points) == 0:
        raw = sum(len(p) for p, _ in fused.per_view)
        raise ValueError(f"place_probes: depth fusion kept no point ({raw} back-projected "
                         f"points from {len(cams)} views, none consistent in "
                         f"{need} other views); check the cameras and the surfels")
    idx = farthest_points(fused.points, cfg.count, seed)
    pts, nrm = fused.points[idx], fused.normals[idx]
    size = float(object_size) if object_size else float(
        np.linalg.norm(fused.points.max(0) - fused.points.min(0)))
    positions = pts + cfg.offset_frac * size * nrm
    spacing = probe_spacing(pts, size)
    radius = query_radius(pts, cfg.neighbours, size)
    return ProbeSet(positions=positions, normals=nrm, res=cfg.res, radius=radius,
                    meta={"placement": {**cfg.__dict__, "object_size": size,
                                        "fused_points": int(len(fused.points)),
                                        "views": [int(i) for i in sel], "spacing": spacing}})
