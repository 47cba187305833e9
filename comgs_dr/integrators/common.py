"""Surfel gathering and analytic ray–surfel evaluation shared by our integrators.

The tracing/compositing passes built on these live in :mod:`.compositing`.
"""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

from ..surfels import kernel as Kn
from ..surfels.shape import is_surfel_shape

def surfel_shapes(scene: mi.Scene, who: str) -> list:
    """All ``surfels`` shapes of a scene; any other shape is a clear error."""
    shapes = list(scene.shapes())
    out = [s for s in shapes if is_surfel_shape(s)]
    others = [s for s in shapes if not is_surfel_shape(s)]
    if others:
        names = ", ".join(f"{type(s).__name__}('{s.id()}')" for s in others[:4])
        raise ValueError(f"{who}: renders only 'surfels' shapes; the scene also has {names}")
    if not out:
        raise ValueError(f"{who}: the scene has no 'surfels' shape")
    return out


def mitsuba_ad_base(name: str = "RBIntegrator"):
    """Mitsuba's Python AD integrator base class (``RBIntegrator``, ``ADIntegrator``)
    built for the active variant."""
    import importlib
    from mitsuba.python.ad.integrators import common as mi_common
    if not issubclass(mi_common.ADIntegrator, mi.CppADIntegrator):
        mi_common = importlib.reload(mi_common)   # Mitsuba's own callback has not run yet
    return getattr(mi_common, name)


@dataclasses.dataclass
class SurfelSample:
    """Per-ray attributes of the surfel in one hit-buffer slot (all [R])."""
    t: mi.Float
    alpha: mi.Float
    normal: mi.Vector3f          # facing the ray
    index: mi.UInt32
    slot: mi.UInt32              # which surfels shape
    valid: mi.Bool


def gather_params(shapes, slot, index, active, names, mode=dr.ReduceMode.Auto):
    """Gather raw parameter fields ``names`` of (shape ``slot``, surfel ``index``).

    With several surfel shapes, each is gathered under its own mask and merged.
    """
    types = {"means": mi.Point3f, "quats": mi.Vector4f, "log_scales": mi.Vector2f,
             "opacity_logit": mi.Float, "albedo": mi.Color3f, "roughness": mi.Float,
             "metallic": mi.Float}
    out = {}
    for j, sh in enumerate(shapes):
        m = active if len(shapes) == 1 else (active & (slot == j))
        for name in names:
            v = dr.gather(types[name], getattr(sh.params, name), index, m, mode=mode)
            out[name] = v if name not in out else dr.select(m, v, out[name])
    return out


def eval_surfel(shapes, slot, index, ray, active, mode=dr.ReduceMode.Auto) -> SurfelSample:
    """Analytic t, α and normal of surfel (slot, index) for ``ray`` (differentiable)."""
    g = gather_params(shapes, slot, index, active,
                      ("means", "quats", "log_scales", "opacity_logit"), mode)
    t_u, t_v, n = Kn.quat_frame(g["quats"])
    s = Kn.scales(g["log_scales"])
    t, u, v, ok = Kn.ray_surfel(ray.o, ray.d, g["means"], t_u, t_v, n, s)
    alpha = Kn.surfel_alpha(Kn.opacity(g["opacity_logit"]), u, v)
    valid = active & ok & (alpha >= Kn.ALPHA_MIN) & dr.isfinite(alpha) & dr.isfinite(t)
    alpha = dr.select(valid, alpha, 0.0)
    return SurfelSample(t=t, alpha=alpha, normal=Kn.facing_normal(n, ray.d), index=index,
                        slot=slot, valid=valid)


def auto_epsilon(scene: mi.Scene, shapes) -> float:
    """Default origin advance: 1/200 of the smallest proxy depth jitter of the
    surfel shapes, so coplanar surfels are found one by one (the tracer also
    enforces a few float32 ulps of the origin per step)."""
    jitter = min(s.proxy_jitter for s in shapes)
    return max(5e-3 * jitter, 1e-12)
