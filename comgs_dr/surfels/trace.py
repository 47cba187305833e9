"""Traced occlusion and radiance of a surfel scene along arbitrary rays (no AD).

Used to bake Surface Octahedral Probes (paper, "SOPs ... initialized via ray tracing") and
as the per-iteration trace baseline of step 2 (IRGS-style): along a ray from x in direction
ω, the front-to-back composite of the surfels gives the occlusion O(ω) = 1 − T = W and the
indirect radiance L_in(ω) = composited radiance-field colour (converted to linear, see
``colorspace.unpremultiplied_to_linear``).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core import colorspace
from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels import composite
from comgs_dr.surfels.composite import trace_composite


def trace_visibility(scene, origins, directions, max_hits: int = 8, epsilon: float = -1.0,
                     radiance: bool = True, colour_space: str = "srgb", max_passes: int = 16):
    """Occlusion [N] and (optionally) linear radiance [N] along N rays.

    Every surfel on a ray is composited (up to T < 1e-4, in passes of ``max_hits``): a
    truncated list made shadows of semi-transparent surfel stacks lighter than they are.

    ``origins``/``directions``: ``mi.Point3f``/``mi.Vector3f`` (unit); every shape of
    ``scene`` must be a ``surfels`` shape. ``colour_space``: the space the radiance field's
    colour was fitted in ('srgb' or 'linear'). Returns (O: mi.Float, L: mi.Color3f | None),
    evaluated (detached).
    """
    if max_hits < 1:
        raise ValueError(f"trace_visibility: max_hits must be ≥ 1, got {max_hits}")
    if colour_space not in ("srgb", "linear"):
        raise ValueError(f"trace_visibility: colour_space must be 'srgb' or 'linear', "
                         f"got {colour_space!r}")
    shapes = composite.surfel_shapes(scene, "trace_visibility")
    eps = epsilon if epsilon > 0 else composite.auto_epsilon(scene, shapes)
    targets = ("color", "weight") if radiance else ("weight",)
    with dr.suspend_grad():
        ray = mi.Ray3f(dr.detach(origins), dr.detach(directions))
        _, out, _, _ = trace_composite(scene, shapes, ray, max_hits, eps, targets,
                                       max_passes=max_passes, keep_hits=False)
        occ = out["weight"]
        rad = None
        if radiance:
            c = out["color"]
            rad = (colorspace.unpremultiplied_to_linear(c, occ) if colour_space == "srgb"
                   else mi.Color3f(dr.maximum(c, 0.0)))
        dr.eval(occ, rad)
    return occ, rad


def trace_visibility_np(scene, origins, directions, chunk: int = 1 << 19, progress=None,
                        **kw):
    """NumPy front end in chunks: [N, 3] origins/directions -> (O [N], L [N, 3] or None).
    ``progress``: optional callable(n_done) for long bakes."""
    origins = np.asarray(origins, np.float32)
    directions = np.asarray(directions, np.float32)
    n = len(origins)
    occ = np.empty(n, np.float32)
    rad = np.empty((n, 3), np.float32) if kw.get("radiance", True) else None
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        o, d = origins[s:e], directions[s:e]
        O, L = trace_visibility(scene, to_jit(mi.Point3f, o.T), to_jit(mi.Vector3f, d.T), **kw)
        occ[s:e] = np.asarray(O)
        if rad is not None:
            rad[s:e] = np.asarray(L).T
        if progress is not None:
            progress(e - s)
    return occ, rad
