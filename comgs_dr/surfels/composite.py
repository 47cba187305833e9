"""Hit-buffer tracing and differentiable front-to-back compositing of surfels.

Paper eq. (Multi-Target Rendering): B = Σ_i T_i α_i b_i, T_i = Π_{j<i} (1 − α_j).

The scheme, in three passes that all recompute t, (u, v), α and b_i
analytically from the gathered parameters (:func:`eval_surfel`):

* :func:`trace_composite` — primal, no AD: trace the surfel proxies, keep up
  to K ordered hits with α ≥ 1/255 per ray (the *hit buffer*; the origin
  advances by t + ε after each hit) and accumulate B in the same symbolic loop.
* :func:`composite_adjoint` — reverse or forward mode over the stored hits,
  without re-tracing. With S_i = Σ_{j>i} T_j α_j b_j (+ T_final·background, a grey level
  or a per-ray radiance)
  = B − Σ_{j≤i} T_j α_j b_j, the derivative of B is
  dB = Σ_i [ T_i α_i db_i + dα_i (T_i b_i − S_i / (1 − α_i)) ],
  so each hit contributes the local surrogate y_i = T_i α_i b_i − α_i S_i/(1−α_i)
  (T_i, S_i, 1−α_i detached), back-propagated with ``dr.backward_from`` or
  pushed forward with ``dr.forward_to`` inside one symbolic loop (compile
  time independent of K, as in Mitsuba's PRB).
* :func:`composite_unrolled` — the obviously-right reference: a Python-unrolled
  loop over K with plain AD. Used by tests to check the adjoint pass.

Gradients flow to every surfel parameter except through changes of the hit
order or hit set (as in 2DGS).
"""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit

from comgs_dr.surfels import kernel as Kn
from comgs_dr.surfels.shape import ensure_proxies, is_surfel_shape

INVALID = 0xFFFFFFFF
# Parameters that a target does not depend on (e.g. albedo for depth) are legal.
_AD_FLAGS = dr.ADFlag.Default | dr.ADFlag.AllowNoGrad
# Reverse mode turns every parameter gather of a hit into a scatter-add (≈35 per hit with
# SH degree 2). ReduceMode.Expand (per-thread copies, no atomics) is no faster on a few CPU
# cores, so Auto stays.
ADJOINT_MODE = dr.ReduceMode.Auto
ULP_STEP = 2.0 ** -21          # ≈ 4 ulps of float32: the smallest origin advance that progresses
BASE_TARGETS = ("color", "weight", "depth", "normal", "albedo", "roughness", "metallic")
_VEC3 = ("color", "normal", "albedo")        # 3-channel buffers; the others are Float


def surfel_shapes(scene: mi.Scene, who: str) -> list:
    """All ``surfels`` shapes of a scene, sorted by id; any other shape is a clear error.

    Sorted because ``mi.load_dict`` loads a scene's children in parallel, so ``scene.shapes()``
    comes in a different order from one load to the next; the slots (and with them which
    random numbers each object's rays take) would follow it and a render would not repeat.
    """
    shapes = sorted(scene.shapes(), key=lambda s: s.id())
    out = [s for s in shapes if is_surfel_shape(s)]
    others = [s for s in shapes if not is_surfel_shape(s)]
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


def auto_epsilon(scene: mi.Scene, shapes) -> float:
    """Default origin advance: 1/200 of the smallest proxy depth jitter of the
    surfel shapes, so coplanar surfels are found one by one (the tracer also
    enforces a few float32 ulps of the origin per step)."""
    jitter = min(s.proxy_jitter for s in shapes)
    return max(5e-3 * jitter, 1e-12)


def _vtype(name):
    """Dr.Jit type of a base buffer in the active variant."""
    return {"color": mi.Color3f, "normal": mi.Vector3f, "albedo": mi.Color3f}.get(name, mi.Float)


def accumulated(targets) -> tuple[str, ...]:
    """Base buffers to accumulate for the requested targets (W always)."""
    need = set(targets) | {"weight"}
    if "depth_unbiased" in need:
        need |= {"depth"}
    return tuple(t for t in BASE_TARGETS if t in need)


def _zero(name, R):
    return dr.zeros(_vtype(name), R)


@dataclasses.dataclass
class HitBuffer:
    """Up to K ordered surfel hits per ray: ``ids``/``slots`` flat [R*K], ``count`` [R];
    ``still_open`` ([R] bool numpy or None): rays whose compositing stopped at the last
    slot while their transmittance was still ≥ ``T_MIN``."""
    ids: mi.UInt32
    slots: mi.UInt32
    count: mi.UInt32
    K: int
    still_open: object = None


def surfel_values(shapes, slot, index, ray, active, names, mode=dr.ReduceMode.Auto):
    """(sample, {name: b_i}) for one hit per ray; differentiable if params are attached.
    ``mode``: how the gathers' adjoint scatter-adds are compiled (see ``ADJOINT_MODE``)."""
    smp = eval_surfel(shapes, slot, index, ray, active, mode)
    vals = {}
    for name in names:
        if name == "weight":
            vals[name] = mi.Float(1.0)
        elif name == "depth":
            vals[name] = smp.t
        elif name == "normal":
            vals[name] = smp.normal
        elif name == "color":
            c = mi.Color3f(0.0)
            for j, sh in enumerate(shapes):
                m = smp.valid if len(shapes) == 1 else (smp.valid & (slot == j))
                cj = Kn.sh_color(sh.params.sh, index, sh.params.sh_coeffs, ray.d, m, mode)
                c = cj if len(shapes) == 1 else dr.select(m, cj, c)
            vals[name] = c
    mats = [m for m in ("albedo", "roughness", "metallic") if m in names]
    if mats:
        vals.update(gather_params(shapes, slot, index, smp.valid, mats, mode))
    return smp, vals


def _opaque(value: float):
    """A scalar as an opaque JIT variable: a literal would be compiled into the kernel, and
    a new value (step 1 draws a random background each step) would recompile the whole
    render every iteration."""
    return dr.opaque(mi.Float, float(value))


def with_background(color, T_final, background):
    """C + T_final · background: ``background`` a grey level (float) or per-ray radiance
    (``mi.Color3f``, e.g. an environment map looked up along the rays)."""
    if isinstance(background, (int, float)):
        return color + T_final * _opaque(background) if background > 0 else color
    return color + T_final * mi.Color3f(background)


def finish(acc: dict, targets, T_final, background=0.0) -> dict:
    """Requested outputs from accumulated buffers (adds background, unbiased depth)."""
    out = {t: acc[t] for t in targets if t in acc}
    if "color" in out:
        out["color"] = with_background(out["color"], T_final, background)
    if "depth_unbiased" in targets:
        W = acc["weight"]
        out["depth_unbiased"] = dr.select(W > 1e-6, acc["depth"] / dr.maximum(W, 1e-6), 0.0)
    return out


def trace_composite(scene, shapes, ray, K: int, eps: float, targets, background=0.0, active=True,
                    max_passes: int = 1, keep_hits: bool = True):
    """Primal pass: hit buffer + accumulated buffers, no AD.

    Each pass traces up to K hits per ray; rays whose K slots are full while still open
    (T ≥ ``T_MIN``) are traced on from their last hit for up to ``max_passes`` passes, so
    every surfel on the ray is composited (1: only the first K, as before). Without
    ``keep_hits`` the hit list is not kept (``ids``/``slots`` None: callers that need only
    the buffers, e.g. visibility rays, save K · passes slots per ray).
    Returns (HitBuffer with K · passes slots, outputs {target: value}, acc {base buffer:
    value}, T_final); ``HitBuffer.still_open`` holds the rays left open ([R] bool numpy).
    """
    names = accumulated(targets)
    ensure_proxies(scene, shapes)
    with dr.suspend_grad():
        ray = mi.Ray3f(dr.detach(ray))
        R = dr.width(ray)            # (an orthographic camera's d is one literal: width 1)
        act = mi.Bool(active) & (dr.zeros(mi.Bool, R) | True)
        state = (dr.full(mi.Float, 1.0, R), dr.zeros(mi.Float, R), {k: _zero(k, R) for k in names})
        ids, slots, count = [], [], np.zeros(R, np.int64)
        for p in range(max(1, max_passes)):
            pids, pslots, pcount, T, t_acc, acc, full = _trace_pass(scene, shapes, ray, K, eps,
                                                                    names, act, state)
            c = np.asarray(pcount)
            if keep_hits:
                ids.append(np.asarray(pids).reshape(R, K))
                slots.append(np.asarray(pslots).reshape(R, K))
            count += c
            open_ = np.asarray(full) & (np.asarray(T) >= Kn.T_MIN)
            state = (T, t_acc, acc)
            if not open_.any():
                break
            act = to_jit(mi.Bool, open_)
        P = p + 1
        hits = HitBuffer(ids=to_jit(mi.UInt32, np.concatenate(ids, 1).ravel()) if keep_hits else None,
                         slots=to_jit(mi.UInt32, np.concatenate(slots, 1).ravel()) if keep_hits else None,
                         count=to_jit(mi.UInt32, count.astype(np.uint32)), K=P * K,
                         still_open=open_)
        out = finish(acc, targets, T, background)
    return hits, out, acc, T


def _trace_pass(scene, shapes, ray, K, eps, names, active, state):
    """One tracing pass of ≤ K hits per ray from (T, t_acc, acc) of the previous one.

    Proxy hits whose surfel rejects the ray (α < 1/255 in the quad's corners) do not take
    a slot; a ray stops after ``64K + 256`` of them (a guard against degenerate geometry,
    counted apart from the hits: a ray through many large, faint quads is not cut short).
    Returns (ids, slots, count, T, t_acc, acc, full: [R] K slots filled).
    """
    R = dr.width(ray)
    rid = dr.arange(mi.UInt32, R)
    ids = dr.full(mi.UInt32, INVALID, R * K)
    slots = dr.zeros(mi.UInt32, R * K)
    ptrs = [mi.ShapePtr(s) for s in shapes]
    o_mag = dr.max(dr.abs(ray.o))                                       # [R] (per ray)
    max_miss = 64 * K + 256

    def cond(act, *_):
        return act

    def body(act, miss, count, T, t_acc, acc):
        r = mi.Ray3f(dr.fma(ray.d, t_acc, ray.o), ray.d, ray.maxt - t_acc, ray.time, ray.wavelengths)
        pi = scene.ray_intersect_preliminary(r, coherent=False, active=act)
        act = act & pi.is_valid()
        index = pi.prim_index // 2
        slot = mi.UInt32(0)
        for j in range(1, len(ptrs)):
            slot = dr.select(pi.shape == ptrs[j], j, slot)
        smp, vals = surfel_values(shapes, slot, index, ray, act, names)
        keep = act & smp.valid
        pos = rid * K + count
        dr.scatter(ids, index, pos, keep)
        dr.scatter(slots, slot, pos, keep)
        w = dr.select(keep, T * smp.alpha, 0.0)                 # T_i α_i
        acc = {k: dr.fma(vals[k], w, acc[k]) for k in names}
        count = dr.select(keep, count + 1, count)
        T = dr.select(keep, T * (1.0 - smp.alpha), T)
        miss = dr.select(act & ~keep, miss + 1, miss)
        # advance past the hit: ε, but at least ~4 float32 ulps of the new origin
        step = dr.maximum(eps, (o_mag + t_acc + pi.t) * ULP_STEP)
        t_acc = dr.select(act, t_acc + pi.t + step, t_acc)
        act = act & (count < K) & (T >= Kn.T_MIN) & (miss < max_miss)
        return act, miss, count, T, t_acc, acc

    T0, t0, acc0 = state
    init = (mi.Bool(active), mi.UInt32(0), dr.zeros(mi.UInt32, R), mi.Float(T0), mi.Float(t0),
            dict(acc0))
    _, _, count, T, t_acc, acc = dr.while_loop(init, cond, body, label="surfel trace+composite")
    dr.eval(ids, slots, count, T, t_acc, acc)
    return ids, slots, count, T, t_acc, acc, count >= K


def composite_hits(shapes, ray, hits: HitBuffer, targets, background=0.0):
    """Primal compositing of a given hit buffer (no AD), e.g. from the rasteriser.

    Returns (outputs {target: value}, acc {base buffer: value}, T_final), as
    :func:`trace_composite` does for the hits it finds itself.
    """
    names = accumulated(targets)
    R = dr.width(hits.count)
    with dr.suspend_grad():
        ray = mi.Ray3f(dr.detach(ray))
        rid = dr.arange(mi.UInt32, R)

        def cond(k, T, acc):
            return k < hits.count

        def body(k, T, acc):
            pos = rid * hits.K + k
            index = dr.gather(mi.UInt32, hits.ids, pos)
            slot = dr.gather(mi.UInt32, hits.slots, pos) if len(shapes) > 1 else mi.UInt32(0)
            smp, vals = surfel_values(shapes, slot, index, ray, k < hits.count, names)
            w = T * smp.alpha                                       # T_i α_i
            acc = {n: dr.fma(vals[n], w, acc[n]) for n in names}
            return k + 1, T * (1.0 - smp.alpha), acc

        _, T, acc = dr.while_loop((mi.UInt32(0), dr.full(mi.Float, 1.0, R),
                                   {k: _zero(k, R) for k in names}), cond, body,
                                  label="surfel composite (hits)")
        dr.eval(T, acc)
        out = finish(acc, targets, T, background)
    return out, acc, T


def composite_adjoint(mode, shapes, ray, hits: HitBuffer, acc: dict, T_final, targets,
                      grad_out: dict | None = None, background=0.0) -> dict:
    """Reverse (``grad_out`` = adjoints of the outputs) or forward mode over stored hits.

    Backward: accumulates parameter gradients (returns {}). Forward: returns the
    tangents {target: dB} of the requested outputs.
    """
    names = accumulated(targets)
    backward = mode == dr.ADMode.Backward
    R = dr.width(hits.count)
    with dr.suspend_grad():
        ray = mi.Ray3f(dr.detach(ray))
        B = dict(acc)
        if "color" in B:
            B["color"] = with_background(B["color"], T_final, background)
        if backward:
            δ = {k: grad_out.get(k, _zero(k, R)) for k in names}
            if "depth_unbiased" in targets and "depth_unbiased" in grad_out:
                W, D, g = acc["weight"], acc["depth"], grad_out["depth_unbiased"]
                ok = W > 1e-6
                iw = dr.select(ok, dr.rcp(dr.maximum(W, 1e-6)), 0.0)
                δ["depth"] = δ["depth"] + g * iw
                δ["weight"] = δ["weight"] - g * D * iw * iw
            δ = {k: _vtype(k)(v) for k, v in δ.items()}
            dr.eval(δ)
        rid = dr.arange(mi.UInt32, R)

        def cond(k, *_):
            return k < hits.count

        def body(k, T, P, tan):
            pos = rid * hits.K + k
            index = dr.gather(mi.UInt32, hits.ids, pos)
            slot = dr.gather(mi.UInt32, hits.slots, pos)
            active = k < hits.count
            with dr.resume_grad():
                smp, vals = surfel_values(shapes, slot, index, ray, active, names, ADJOINT_MODE)
                α = smp.alpha
                αd = dr.detach(α)
                w = T * αd
                S = {n: B[n] - P[n] - w * dr.detach(vals[n]) for n in names}
                inv = dr.rcp(1.0 - αd)
                y = {n: T * α * vals[n] - α * S[n] * inv for n in names}
                if backward:
                    obj = mi.Float(0.0)
                    for n in names:
                        obj += dr.sum(δ[n] * y[n]) if n in _VEC3 else δ[n] * y[n]
                    dr.backward_from(obj, flags=_AD_FLAGS)
                else:
                    ts = dr.forward_to(*[y[n] for n in names], flags=_AD_FLAGS)
                    ts = ts if isinstance(ts, tuple) else (ts,)
                    tan = {n: tan[n] + t for n, t in zip(names, ts)}
            P = {n: P[n] + w * dr.detach(vals[n]) for n in names}
            T = T * (1.0 - αd)
            return k + 1, T, P, tan

        state = (mi.UInt32(0), dr.full(mi.Float, 1.0, R), {n: _zero(n, R) for n in names},
                 {n: _zero(n, R) for n in names} if not backward else {})
        _, _, _, tan = dr.while_loop(state, cond, body, label=f"surfel composite ({mode.name})")
    if backward:
        return {}
    out = {t: tan[t] for t in targets if t in tan}
    if "depth_unbiased" in targets:
        W, D = acc["weight"], acc["depth"]
        ok = W > 1e-6
        iw = dr.select(ok, dr.rcp(dr.maximum(W, 1e-6)), 0.0)
        out["depth_unbiased"] = tan["depth"] * iw - D * tan["weight"] * iw * iw
    return out


def composite_unrolled(shapes, ray, hits: HitBuffer, targets, background=0.0) -> dict:
    """Reference: Python-unrolled front-to-back loop over K with plain AD.

    Slow to compile for large K; use :func:`composite_adjoint` in pipelines.
    Returns {target: value} including ``weight``.
    """
    names = accumulated(targets)
    R = dr.width(hits.count)
    T = dr.full(mi.Float, 1.0, R)
    acc = {n: _zero(n, R) for n in names}
    rid = dr.arange(mi.UInt32, R)
    for k in range(hits.K):
        pos = rid * hits.K + k
        index = dr.gather(mi.UInt32, hits.ids, pos)
        slot = dr.gather(mi.UInt32, hits.slots, pos)
        smp, vals = surfel_values(shapes, slot, index, ray, k < hits.count, names)
        w = T * smp.alpha
        acc = {n: acc[n] + w * vals[n] for n in names}
        T = T * (1.0 - smp.alpha)
    out = finish(acc, targets, T, background)
    out["weight"] = acc["weight"]
    return out
