"""Pure Dr.Jit math for 2D Gaussian surfels (no plugins, no state).

Paper, "Multi-Target Rendering": a surfel i has centre p_i, rotation q_i and two
scales (s_u, s_v). Its tangent frame is the columns of R(q_i) = [t_u, t_v, n].
A ray o + t·d meets the surfel plane at t = ((p−o)·n)/(d·n); local coordinates
u = ((x−p)·t_u)/s_u, v = ((x−p)·t_v)/s_v; Gaussian weight G = exp(−(u²+v²)/2);
alpha α = min(o_i·G, ALPHA_MAX). Every function is written for any JIT variant
(use of mi.Float/mi.Vector3f only) and is differentiable.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

ALPHA_MIN = 1.0 / 255.0     # 2DGS: contributions below this are skipped
ALPHA_MAX = 0.99            # 2DGS: alpha clamp, keeps T > 0 and gradients finite
T_MIN = 1e-4                # 2DGS: stop compositing once transmittance falls below
LOG_SCALE_RANGE = (-20.0, 12.0)   # clamp of log-scales (≈2e-9 .. 1.6e5 scene units)
LOGIT_RANGE = (-30.0, 30.0)       # clamp of opacity logits (exp stays finite)
QUAD_SIGMA = 3.0            # the tracing proxy quad spans ±3σ in both tangent axes

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
         0.3731763325901154, -0.4570457994644658, 1.445305721320277,
         -0.5900435899266435)


def clamp_closed(x, lo, hi):
    """``x`` clamped to [lo, hi], with gradient 1 on the closed interval (0 outside).
    ``dr.clip`` has gradient 0 *at* the bounds too, and step 2 clamps its materials to the
    bounds after every step: a surfel at metallic 0 or albedo 1 would get no gradient through
    ``mi.render`` again (an optimiser would never move it), though the one-sided derivative is
    what a projected-gradient step needs."""
    return dr.select((x >= lo) & (x <= hi), x, dr.clip(x, lo, hi))


def sigmoid(x):
    """Logistic function with clamped input (Dr.Jit has no dr.sigmoid)."""
    x = dr.clip(x, LOGIT_RANGE[0], LOGIT_RANGE[1])
    return dr.rcp(1.0 + dr.exp(-x))


def opacity(opacity_logit):
    return sigmoid(opacity_logit)


def scales(log_scales):
    """[N] Vector2f of standard deviations s_u, s_v from log-scales (clamped)."""
    return dr.exp(dr.clip(log_scales, LOG_SCALE_RANGE[0], LOG_SCALE_RANGE[1]))


def quat_frame(q):
    """Tangent frame (t_u, t_v, n) = columns of R(q) for a w-first quaternion.

    q is normalised here; a zero quaternion gives the identity frame (finite).
    """
    l2 = dr.squared_norm(q)
    ok = l2 > 1e-24
    inv = dr.select(ok, dr.rsqrt(dr.select(ok, l2, 1.0)), 0.0)
    w = dr.select(ok, q.x * inv, 1.0)
    x, y, z = q.y * inv, q.z * inv, q.w * inv
    t_u = mi.Vector3f(1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y))
    t_v = mi.Vector3f(2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x))
    n = mi.Vector3f(2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))
    return t_u, t_v, n


def ray_surfel(o, d, p, t_u, t_v, n, s):
    """Ray–surfel intersection in the surfel plane.

    Returns (t, u, v, ok): ray distance, scale-normalised local coordinates, and
    a mask that is False for rays parallel to the plane (then t = u = v = 0).
    """
    denom = dr.dot(d, n)
    ok = dr.abs(denom) > 1e-12
    t = dr.dot(p - o, n) / dr.select(ok, denom, 1.0)
    x = dr.fma(d, t, o) - p
    u = dr.dot(x, t_u) / s.x
    v = dr.dot(x, t_v) / s.y
    return dr.select(ok, t, 0.0), dr.select(ok, u, 0.0), dr.select(ok, v, 0.0), ok


def gaussian(u, v):
    return dr.exp(-0.5 * (u * u + v * v))


def surfel_alpha(op, u, v):
    """α = min(o·G(u, v), ALPHA_MAX)."""
    return dr.minimum(op * gaussian(u, v), ALPHA_MAX)


def facing_normal(n, d):
    """Surfel normal flipped to face the incoming ray (2DGS convention)."""
    return dr.select(dr.dot(n, d) > 0, -n, n)


def sh_basis(d, degree: int) -> list:
    """Real SH basis values in the 3DGS convention, K = (degree+1)^2 entries."""
    x, y, z = d.x, d.y, d.z
    out = [mi.Float(SH_C0) + 0 * x]
    if degree > 0:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy),
                SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree > 2:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z,
                SH_C3[2] * y * (4 * zz - xx - yy), SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                SH_C3[4] * x * (4 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3 * yy)]
    return out


def sh_color(sh, index, K: int, d, active=True, mode=dr.ReduceMode.Auto):
    """Colour max(Σ_k Y_k(d) f_k + 0.5, 0) of surfel ``index``; sh flat [N, K, 3]."""
    degree = {1: 0, 4: 1, 9: 2, 16: 3}[K]
    basis = sh_basis(d, degree)
    c = mi.Color3f(0.0)
    base = index * K
    for k in range(K):
        f = dr.gather(mi.Color3f, sh, base + k, active, mode=mode)
        c = dr.fma(f, basis[k], c)
    return dr.maximum(c + 0.5, 0.0)
