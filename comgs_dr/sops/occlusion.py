"""Occlusion caching for composition (paper, "Occlusion Caching", sec. 4.1).

* :func:`shadow_region_probes` — Surface Octahedral Probes on the *scene* surface around a
  placed object: surface points (multi-view-consistent G-buffer points of the scene, see
  ``sops.placement``) inside the object's bounding box scaled ×``box_factor`` (6 in the
  paper) that face the object (n·(c − x) > 0), thinned by farthest point sampling and
  offset along the normal. Their normals are refitted (:func:`plane_normals`): the fused
  points' own normals scatter by ~30° on a flat ground, and the shadow ratio weights the
  light by the receiver's cosine.
* :func:`transform_probes` — an object's own SOPs carried into the world by its placement:
  positions and normals transformed, each octahedral texture resampled so that a world
  direction reads the texel of the object-space direction Rᵀω (bilinear, 2×2 supersampled).
* :func:`trace_occlusion` — occlusion textures O [P, R, R] of a probe set against one
  occluder (the surfels of one placed object), texel-supersampled.
* :func:`combine` — occlusion of several independent occluders, 1 − Π_j (1 − O_j).
* :func:`can_occlude` — whether an occluder's bounding sphere subtends at least
  ``min_texels`` octahedral texels from some probe (else its occlusion texture is zero and
  is not traced).

Occlusion per (receiver, occluder) pair is what the composition caches, so moving one
object re-traces only the pairs it is part of.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core import octahedral as octa
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.similarity import Similarity
from comgs_dr.sops.bake import bake
from comgs_dr.sops.placement import farthest_points, query_radius
from comgs_dr.sops.probes import ProbeSet

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ShadowConfig:
    count: int = 10000               # shadow-region probes per object (sec. 4.1: 10k)
    # 32² texels, one ray each: the same 1024 rays per probe as 16² × 2² supersampling, but
    # sharper low-sun shadows at the same edit time. The paper's SOPs use 16².
    res: int = 32                    # octahedral texels per side
    box_factor: float = 6.0          # region = object bounds × 6 around the object's centre
    offset_frac: float = 0.01        # probe offset along the normal, × object size
    supersample: int = 1             # directions per texel side when tracing
    neighbours: float = 8.0          # probes within the query radius
    normal_radius_frac: float = 0.15  # probe normals: plane fit to the surface points within
                                      # this × the object's diagonal (0: the points' own)

    def __post_init__(self):
        if self.count < 1 or self.res < 2 or self.box_factor < 1 or self.supersample < 1:
            raise ValueError(f"ShadowConfig: need count ≥ 1, res ≥ 2, box_factor ≥ 1, "
                             f"supersample ≥ 1, got {self}")


def region_box(lo, hi, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """The box of ``factor`` × the extent of [lo, hi] about its centre."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c, half = (lo + hi) / 2, (hi - lo) / 2 * factor
    return c - half, c + half


def shadow_region_probes(points, normals, lo, hi, cfg: ShadowConfig = ShadowConfig(),
                         seed: int = 0, name: str = "object") -> ProbeSet:
    """Probe set (untextured) on the scene points [M, 3] (unit normals [M, 3]) in the
    shadow region of an object with world bounds [lo, hi]. ValueError when no scene point
    lies in the region facing the object (nothing to receive its shadow)."""
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    blo, bhi = region_box(lo, hi, cfg.box_factor)
    centre = (np.asarray(lo) + np.asarray(hi)) / 2
    size = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    inside = np.all((points >= blo) & (points <= bhi), axis=1)
    facing = ((centre - points) * normals).sum(1) > 0.0
    keep = np.nonzero(inside & facing)[0]
    if len(keep) == 0:
        raise ValueError(f"shadow probes of {name!r}: no scene surface point faces the object "
                         f"inside its region {blo.round(3).tolist()}–{bhi.round(3).tolist()} "
                         f"({int(inside.sum())} points inside, none facing it); is the "
                         f"placement inside the reconstructed scene?")
    if len(keep) < cfg.count:       # every facing point gets a probe: the most there can be
        log.info("shadow probes of %r: %d of the %d asked, one on every scene surface point "
                 "(depth fused from the training views) that faces the object inside its "
                 "region", name, len(keep), cfg.count)
    idx = keep[farthest_points(points[keep], cfg.count, seed)]
    pts, nrm = points[idx], normals[idx]
    if cfg.normal_radius_frac > 0:
        nrm = plane_normals(points, normals, pts, cfg.normal_radius_frac * size)
    return ProbeSet(positions=pts + cfg.offset_frac * size * nrm, normals=nrm, res=cfg.res,
                    radius=query_radius(pts, cfg.neighbours, size),
                    meta={"shadow_region": {"object": name, "box": [blo.tolist(), bhi.tolist()],
                                            "candidates": int(len(keep)), **cfg.__dict__}})


def plane_normals(points, normals, at, radius: float, iterations: int = 6,
                  max_points: int = 256) -> np.ndarray:
    """[M, 3] unit normals at ``at`` [M, 3]: a plane fitted to the surface ``points`` [N, 3]
    within ``radius`` of each (the nearest ``max_points`` of them), turned to the side of
    their mean ``normals``.

    Why: fused depth points lie on the surface within their depth noise, so a plane fit over
    a few hundred of them is flat to a few degrees where their own normals (alpha-blended
    surfel normals) scatter by tens of degrees. The fit is reweighted ``iterations`` times by
    the residuals (Tukey's biweight, cut at 3 × the median residual), so points across an
    edge — a ground meeting a wall — drop out.
    Fewer than 3 points in reach: the nearest point's own normal. All probes at once
    (batched 3×3 eigendecompositions)."""
    from scipy.spatial import cKDTree
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    at = np.atleast_2d(np.asarray(at, np.float64))
    tree = cKDTree(points)
    k = min(max_points, len(points))
    dist, idx = tree.query(at, k=k, distance_upper_bound=radius)
    dist, idx = dist.reshape(len(at), k), idx.reshape(len(at), k)
    valid = np.isfinite(dist)                                       # [M, k]
    q = points[np.minimum(idx, len(points) - 1)]                    # [M, k, 3]
    w = valid.astype(np.float64)
    for _ in range(iterations + 1):
        c = (w[..., None] * q).sum(1) / np.maximum(w.sum(1), 1e-30)[:, None]
        dq = q - c[:, None]
        cov = np.einsum("mk,mki,mkj->mij", w, dq, dq)
        n = np.linalg.eigh(cov)[1][..., 0]                          # [M, 3] smallest
        r = np.abs((dq * n[:, None]).sum(-1))
        med = np.nanmedian(np.where(valid, r, np.nan), axis=1) if valid.any(1).all() else \
            np.array([np.median(ri[vi]) if vi.any() else 1.0 for ri, vi in zip(r, valid)])
        cut = 3.0 * np.maximum(med, 1e-12)[:, None]
        w = valid * (np.where(r < cut, (1.0 - (r / cut) ** 2) ** 2, 0.0) + 1e-9)
    ref = (normals[np.minimum(idx, len(points) - 1)] * valid[..., None]).sum(1)
    n = np.where(((n * ref).sum(1) >= 0)[:, None], n, -n)
    few = valid.sum(1) < 3
    if few.any():
        n[few] = normals[tree.query(at[few])[1]]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def transform_probes(probes: ProbeSet, sim: Similarity, supersample: int = 2) -> ProbeSet:
    """``probes`` (object space) placed by ``sim``: world positions/normals, radius × scale,
    textures resampled to world directions (see the module docstring)."""
    if probes.texture is None:
        raise ValueError("transform_probes: the probes have no textures")
    R, P, s = probes.res, probes.count, int(supersample)
    atlas = to_jit(mi.Float, probes.bordered().ravel())
    # world directions: s×s stratified per texel (texel-major), object-space = Rᵀ ω
    j = (np.arange(s) + 0.5) / s
    ty, tx, sy, sx = np.meshgrid(np.arange(R), np.arange(R), j, j, indexing="ij")
    uv = np.stack([((tx + sx) / R).ravel(), ((ty + sy) / R).ravel()], -1)
    d_world = octa.uv_to_dir_np(uv)                                        # [R²s², 3]
    d_obj = d_world @ np.asarray(sim.rotation)                             # rows: Rᵀ ω
    uv_obj = octa.dir_to_uv_np(d_obj).astype(np.float32)                   # [R²s², 2]
    n = len(uv_obj)
    tile = dr.arange(mi.UInt32, P * n) // n
    k = dr.arange(mi.UInt32, P * n) % n
    uvv = dr.gather(mi.Point2f, to_jit(mi.Point2f, uv_obj.T), k)
    val = octa.lookup(atlas, octa.bilinear_taps(tile, uvv, R), 4)         # [P*n] Vector4f
    tex = np.asarray(val).T.reshape(P, R * R, s * s, 4).mean(2).reshape(P, R, R, 4)
    sc = float(sim.scale)
    return ProbeSet(positions=sim.points(probes.positions), normals=sim.directions(probes.normals),
                    res=R, radius=probes.radius * sc, texture=tex.astype(np.float32),
                    meta={**probes.meta, "placed": sim.matrix.tolist()})


def can_occlude(probes: ProbeSet, centre, radius: float, min_texels: float = 0.25) -> bool:
    """False when a sphere (``centre``, ``radius``) bounding an occluder subtends less than
    ``min_texels`` texels' solid angle from every probe (its occlusion would vanish)."""
    d = np.linalg.norm(probes.positions - np.asarray(centre)[None], axis=1)
    if np.any(d <= radius):
        return True
    omega = 2 * np.pi * (1 - np.sqrt(1 - (radius / d.min()) ** 2))
    return omega >= min_texels * 4 * np.pi / probes.res ** 2


def trace_occlusion(probes: ProbeSet, occluder_scene, supersample: int = 2,
                    max_hits: int = 32, progress: bool = False) -> np.ndarray:
    """O [P, R, R] of ``probes`` against the surfels of ``occluder_scene`` (positions only
    are used; the probe set is not modified)."""
    tmp = ProbeSet(positions=probes.positions, normals=probes.normals, res=probes.res,
                   radius=probes.radius)
    bake(occluder_scene, tmp, max_hits=max_hits, supersample=supersample, radiance=False,
         progress=progress)
    return np.ascontiguousarray(tmp.texture[..., 3])


def combine(occlusions) -> np.ndarray:
    """1 − Π_j (1 − O_j) of independent occluders' textures (same shape); zeros for none."""
    occlusions = list(occlusions)
    if not occlusions:
        raise ValueError("combine: no occlusion textures")
    free = np.ones_like(occlusions[0], np.float64)
    for o in occlusions:
        free *= 1.0 - np.clip(o, 0.0, 1.0)
    return (1.0 - free).astype(np.float32)
