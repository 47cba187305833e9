"""Rays cast into a surfel set: where each ray meets the surface (no AD).

The same front-to-back composite as the ``surfel_gbuffer`` integrator
(:func:`~comgs_dr.surfels.composite.trace_composite`), for arbitrary rays rather than a
camera's pixels: per ray the accumulated opacity W and the *median* depth, where W first
reaches a level (e.g. 0.5: the ray "hits" there), with that surfel's normal. The median
depth is the first surface: the unbiased (mean) depth Σ T_i α_i t_i / W, also returned,
mixes in whatever the remaining transmittance sees behind it (a sphere of 0.95-opaque
surfels: its back, up to 0.4 radii deeper). Used by ``comgs place`` (a pixel's ray, and
rays along the up vector under an object's surfels).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels import composite
from comgs_dr.surfels.params import SurfelParams
from comgs_dr.surfels.shape import SurfelShapeBase


def trace_scene(params: SurfelParams, name: str = "surfels") -> mi.Scene:
    """A Mitsuba scene holding only ``params`` as one ``surfels`` shape (for :func:`cast`)."""
    return mi.load_dict({"type": "scene", name: SurfelShapeBase.from_params(params, id=name)})


def cast(scene: mi.Scene, origins, directions, max_hits: int = 16, max_passes: int = 8,
         level: float = 0.5, chunk: int = 1 << 17) -> dict:
    """Cast N rays ([N, 3] origins, [N, 3] directions, normalised here) into the surfel
    ``scene``. Returns numpy arrays:

    * ``weight`` [N]: the accumulated opacity W of every surfel on the ray;
    * ``depth`` [N]: the *median* depth, the distance (along the unit direction) of the
      surfel at which W first reaches ``level`` (NaN where it never does): the first
      surface, whatever lies behind it;
    * ``normal`` [N, 3]: that surfel's normal, facing the ray (0 where none);
    * ``mean_depth`` [N]: the unbiased composited depth Σ T_i α_i t_i / W (the
      ``surfel_gbuffer``'s ``depth_unbiased``), which also averages what the remaining
      transmittance sees behind the first surface.

    Every surfel on a ray is composited up to transmittance ~1e-4 (passes of ``max_hits``,
    at most ``max_passes``)."""
    if max_hits < 1 or max_passes < 1:
        raise ValueError(f"cast: max_hits and max_passes must be >= 1, got {max_hits}, "
                         f"{max_passes}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"cast: level must be in (0, 1), got {level!r}")
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    if o.shape != d.shape:
        raise ValueError(f"cast: {len(o)} origins but {len(d)} directions")
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    n = len(o)
    out = {"weight": np.zeros(n), "depth": np.full(n, np.nan), "normal": np.zeros((n, 3)),
           "mean_depth": np.zeros(n)}
    if n == 0:
        return out
    shapes = composite.surfel_shapes(scene, "raycast.cast")
    eps = composite.auto_epsilon(scene, shapes)
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        with dr.suspend_grad():
            ray = mi.Ray3f(to_jit(mi.Point3f, o[s:e].T.astype(np.float32)),
                           to_jit(mi.Vector3f, d[s:e].T.astype(np.float32)))
            hits, res, _, _ = composite.trace_composite(
                scene, shapes, ray, max_hits, eps, ("weight", "depth_unbiased"),
                max_passes=max_passes, keep_hits=True)
            t_med, n_med, found = _crossing(shapes, ray, hits, level)
            dr.eval(res["weight"], res["depth_unbiased"], t_med, n_med, found)
        hit = np.asarray(found, bool).reshape(-1)
        out["weight"][s:e] = np.asarray(res["weight"], np.float64).reshape(-1)
        out["mean_depth"][s:e] = np.asarray(res["depth_unbiased"], np.float64).reshape(-1)
        out["depth"][s:e] = np.where(hit, np.asarray(t_med, np.float64).reshape(-1), np.nan)
        nr = np.asarray(n_med, np.float64).reshape(3, -1).T                 # [3, R] -> [R, 3]
        ln = np.linalg.norm(nr, axis=1, keepdims=True)
        out["normal"][s:e] = np.where(hit[:, None] & (ln > 1e-12), nr / np.maximum(ln, 1e-30),
                                      0.0)
    return out


def _crossing(shapes, ray, hits, level: float):
    """(t, normal, found) of the hit at which each ray's accumulated opacity first reaches
    ``level``, walking its ordered hit buffer front to back."""
    R = dr.width(hits.count)
    rid = dr.arange(mi.UInt32, R)

    def cond(k, T, t, nrm, found):
        return (k < hits.count) & ~found

    def body(k, T, t, nrm, found):
        pos = rid * hits.K + k
        index = dr.gather(mi.UInt32, hits.ids, pos)
        slot = dr.gather(mi.UInt32, hits.slots, pos) if len(shapes) > 1 else mi.UInt32(0)
        smp = composite.eval_surfel(shapes, slot, index, ray, k < hits.count)
        T = T * (1.0 - smp.alpha)
        cross = smp.valid & (1.0 - T >= level)
        return (k + 1, T, dr.select(cross, smp.t, t), dr.select(cross, smp.normal, nrm),
                found | cross)

    _, _, t, nrm, found = dr.while_loop(
        (mi.UInt32(0), dr.full(mi.Float, 1.0, R), dr.zeros(mi.Float, R),
         dr.zeros(mi.Vector3f, R), dr.zeros(mi.Bool, R)), cond, body,
        label="surfel median depth")
    return t, nrm, found
