"""Hit-buffer tracing and front-to-back compositing shared by our integrators.

DESIGN §3: trace *without* AD to fill a buffer of up to K surfel ids per ray
(the origin advances by t + ε after each hit; Mitsuba rays have no mint), then
composite front to back in a Python-unrolled loop over K *with* AD, recomputing
t, (u, v) and α analytically from the gathered parameters. Gradients thus flow
to every surfel parameter except through changes of visibility order.
"""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

from ..surfels import kernel as Kn
from ..surfels.shape import SurfelShape

INVALID = 0xFFFFFFFF


def surfel_shapes(scene: mi.Scene, who: str) -> list[SurfelShape]:
    """All ``surfels`` shapes of a scene; any other shape is a clear error."""
    shapes = list(scene.shapes())
    out = [s for s in shapes if isinstance(s, SurfelShape)]
    others = [s for s in shapes if not isinstance(s, SurfelShape)]
    if others:
        names = ", ".join(f"{type(s).__name__}('{s.id()}')" for s in others[:4])
        raise ValueError(f"{who}: renders only 'surfels' shapes; the scene also has {names}")
    if not out:
        raise ValueError(f"{who}: the scene has no 'surfels' shape")
    return out


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


@dataclasses.dataclass
class HitBuffer:
    """Up to K ordered surfel hits per ray: ids/slots are flat [R*K], count is [R]."""
    ids: mi.UInt32
    slots: mi.UInt32
    count: mi.UInt32
    K: int

    def slot(self, k: int):
        """(index, shape slot, valid) of the k-th hit of every ray."""
        r = dr.arange(mi.UInt32, dr.width(self.count))
        pos = r * self.K + k
        idx = dr.gather(mi.UInt32, self.ids, pos)
        slot = dr.gather(mi.UInt32, self.slots, pos)
        return idx, slot, k < self.count


@dr.syntax
def trace_hits(scene, shapes, ray, K: int, eps: float, active=True) -> HitBuffer:
    """Fill the hit buffer: ordered surfel hits with α ≥ ALPHA_MIN, until T < T_MIN.

    Runs without AD; the result is evaluated so that a backward pass never
    re-traces. ``eps`` advances the origin past each hit (scene units).
    """
    with dr.suspend_grad():
        ray = mi.Ray3f(dr.detach(ray))
        R = dr.width(ray.d)
        rid = dr.arange(mi.UInt32, R)
        ids = dr.full(mi.UInt32, INVALID, R * K)
        slots = dr.zeros(mi.UInt32, R * K)
        count = dr.zeros(mi.UInt32, R)
        T = mi.Float(1.0)
        t_acc = mi.Float(0.0)
        act = mi.Bool(active) & (R > 0)
        ptrs = [mi.ShapePtr(s) for s in shapes]
        it = mi.UInt32(0)
        max_iter = 8 * K + 16   # guards against a ray stuck on degenerate geometry
        while act:
            r = mi.Ray3f(dr.fma(ray.d, t_acc, ray.o), ray.d, ray.maxt - t_acc, ray.time, ray.wavelengths)
            pi = scene.ray_intersect_preliminary(r, coherent=False, active=act)
            act &= pi.is_valid()
            index = pi.prim_index // 2
            slot = mi.UInt32(0)
            for j in range(1, len(ptrs)):
                slot = dr.select(pi.shape == ptrs[j], j, slot)
            smp = eval_surfel(shapes, slot, index, ray, act)
            keep = act & smp.valid
            pos = rid * K + count
            dr.scatter(ids, index, pos, keep)
            dr.scatter(slots, slot, pos, keep)
            count[keep] = count + 1
            T[keep] = T * (1.0 - smp.alpha)
            t_acc[act] = t_acc + pi.t + eps
            it += 1
            act &= (count < K) & (T >= Kn.T_MIN) & (it < max_iter)
        dr.eval(ids, slots, count)
    return HitBuffer(ids=ids, slots=slots, count=count, K=K)


def auto_epsilon(scene: mi.Scene) -> float:
    """Default origin advance: 1e-5 of the scene's bounding-box diagonal."""
    bb = scene.bbox()
    diag = float(dr.norm(bb.max - bb.min)) if bb.valid() else 1.0
    return max(1e-5 * diag, 1e-7)
