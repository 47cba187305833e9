"""Rays cast into a surfel set: where each ray meets the surface (no AD).

The same front-to-back composite as the ``surfel_gbuffer`` integrator
(:func:`~comgs_dr.surfels.composite.trace_composite`), for arbitrary rays rather than a
camera's pixels: per ray the accumulated opacity W, the unbiased depth (Σ T_i α_i t_i / W,
the distance along the unit direction) and the composited normal (facing the ray). A ray
"hits" where W reaches the caller's threshold (e.g. 0.5). Used by ``comgs place`` (a
pixel's ray, and rays along the up vector under an object's surfels).
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
         chunk: int = 1 << 18) -> dict:
    """Cast N rays ([N, 3] origins, [N, 3] directions, normalised here) into the surfel
    ``scene``; returns numpy {"weight" [N], "depth" [N] (along the unit direction; 0 where
    W ≈ 0), "normal" [N, 3] (unit, facing the ray; 0 where W ≈ 0)}. Every surfel on a ray is
    composited up to transmittance ~1e-4 (passes of ``max_hits``, at most ``max_passes``)."""
    if max_hits < 1 or max_passes < 1:
        raise ValueError(f"cast: max_hits and max_passes must be >= 1, got {max_hits}, "
                         f"{max_passes}")
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    if o.shape != d.shape:
        raise ValueError(f"cast: {len(o)} origins but {len(d)} directions")
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    n = len(o)
    out = {"weight": np.zeros(n), "depth": np.zeros(n), "normal": np.zeros((n, 3))}
    if n == 0:
        return out
    shapes = composite.surfel_shapes(scene, "raycast.cast")
    eps = composite.auto_epsilon(scene, shapes)
    targets = ("weight", "depth_unbiased", "normal")
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        with dr.suspend_grad():
            ray = mi.Ray3f(to_jit(mi.Point3f, o[s:e].T.astype(np.float32)),
                           to_jit(mi.Vector3f, d[s:e].T.astype(np.float32)))
            _, res, _, _ = composite.trace_composite(scene, shapes, ray, max_hits, eps, targets,
                                                     max_passes=max_passes, keep_hits=False)
            dr.eval(res["weight"], res["depth_unbiased"], res["normal"])
        w = np.asarray(res["weight"], np.float64).reshape(-1)
        nr = np.asarray(res["normal"], np.float64).reshape(3, -1).T         # [3, R] -> [R, 3]
        ln = np.linalg.norm(nr, axis=1, keepdims=True)
        out["weight"][s:e] = w
        out["depth"][s:e] = np.asarray(res["depth_unbiased"], np.float64).reshape(-1)
        out["normal"][s:e] = np.where(ln > 1e-12, nr / np.maximum(ln, 1e-30), 0.0)
    return out
