"""Simplified Disney BRDF of ComGS (paper eq. render_equation) and hemisphere samplers.

The outgoing radiance of a shading point is estimated as

    C(ω_o) = ∫_Ω f(ω_o, ω_i) · L(ω_i) · (ω_i·n) dω_i  ≈  (2π/S) · Σ_s f · L · cos

with uniform hemisphere samples (the paper's estimator); cosine and GGX visible-normal
samplers give lower-variance alternatives (divide by :func:`pdf_*` instead of 1/2π).

BRDF (simplified Disney: Lambert + GGX; the diffuse lobe has no (1−F) weight):

    f = a·(1−m)/π  +  F(ω_o·h) · D(h) · G2(ω_o, ω_i) / (4 |n·ω_o| |n·ω_i|)
    F0 = 0.04·(1−m) + a·m,   F = F0 + (1−F0)(1 − ω_o·h)^5          (Schlick)
    D  = α² / (π ((n·h)²(α²−1) + 1)²)                                 (GGX / Trowbridge–Reitz)
    G2 = 1 / (1 + Λ(ω_o) + Λ(ω_i))                  (*height-correlated* Smith GGX)

with α = max(r², ALPHA_MIN): the clamp keeps roughness 0 finite (a very sharp lobe, not a
delta) and makes ∂f/∂r = 0 for r < √ALPHA_MIN. G2/(4 cos_o cos_i) is evaluated in the
closed "visibility" form 0.5 / (cos_i·s_o + cos_o·s_i), s = √(cos²(1−α²) + α²), which is
finite at grazing angles; ω_o·h = √((1 + ω_o·ω_i)/2) makes f bitwise reciprocal.
f is zero when n·ω_o ≤ 0 or n·ω_i ≤ 0. Known property of this model: with a = 1 and
m = 0 the diffuse lobe alone has albedo 1, so diffuse + specular exceeds 1 by the
specular albedo (≈ F0 near normal incidence, up to ≈ 0.9 at grazing ω_o for
r → 0).

Everything is Dr.Jit math on ``mi.Float``/``mi.Vector3f``/``mi.Color3f`` (any JIT
variant) and differentiable w.r.t. albedo, roughness and metallic. Sampling happens in
the local frame (z = normal); see :func:`frame_from_normal`.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = [
    "ALPHA_MIN", "ggx_alpha", "fresnel_schlick", "ggx_d", "smith_g1", "smith_g",
    "eval_brdf", "eval_brdf_split", "frame_from_normal", "to_local", "to_world",
    "sample_uniform_hemisphere", "pdf_uniform_hemisphere",
    "sample_cosine_hemisphere", "pdf_cosine_hemisphere",
    "sample_ggx_vndf", "pdf_ggx_vndf", "hammersley", "rotated_hammersley",
]

ALPHA_MIN = 1e-3           # lower clamp of the GGX α (roughness 0 → α = 1e-3, finite D)
_COS_EPS = 1e-12           # cosines are clamped to this before dividing (AD-safe)


# ---------------------------------------------------------------------------------------
# Building blocks

def ggx_alpha(roughness):
    """GGX α = max(roughness², ALPHA_MIN) (Disney's perceptual remapping)."""
    return dr.maximum(roughness * roughness, ALPHA_MIN)


def fresnel_schlick(f0, cos_theta):
    """Schlick's Fresnel F0 + (1 − F0)(1 − cos)^5; cos is clamped to [0, 1]."""
    x = 1.0 - dr.clip(cos_theta, 0.0, 1.0)
    x2 = x * x
    return f0 + (1.0 - f0) * (x2 * x2 * x)


def ggx_d(alpha, cos_h):
    """GGX normal distribution D(h) (normalised: ∫ D(h) cos_h dω_h = 1); 0 for cos_h ≤ 0."""
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    t = c2 * (a2 - 1.0) + 1.0                      # ∈ [α², 1] for c2 ∈ [0, 1]
    return dr.select(cos_h > 0.0, a2 / (dr.pi * t * t), 0.0)


def _smith_s(alpha, cos):
    """s = √(cos²(1−α²) + α²) = cos·√(1 + α² tan²θ); Λ = (s − cos)/(2 cos)."""
    a2 = alpha * alpha
    return dr.sqrt(dr.maximum(cos * cos * (1.0 - a2) + a2, 0.0))


def smith_g1(alpha, cos):
    """Smith GGX masking G1 = 2 cos / (cos + s); 0 for cos ≤ 0."""
    c = dr.maximum(cos, 0.0)
    return dr.select(cos > 0.0, 2.0 * c / (c + _smith_s(alpha, c)), 0.0)


def smith_g(alpha, cos_o, cos_i):
    """Height-correlated Smith GGX masking-shadowing G2 = 1/(1 + Λ_o + Λ_i)
    = 2 cos_o cos_i / (cos_i s_o + cos_o s_i); 0 if either cosine is ≤ 0."""
    co, ci = dr.maximum(cos_o, _COS_EPS), dr.maximum(cos_i, _COS_EPS)
    g = 2.0 * co * ci / (ci * _smith_s(alpha, co) + co * _smith_s(alpha, ci))
    return dr.select((cos_o > 0.0) & (cos_i > 0.0), g, 0.0)


# ---------------------------------------------------------------------------------------
# BRDF

def eval_brdf_split(albedo, roughness, metallic, n, wo, wi):
    """(diffuse, specular) parts of f(ω_o, ω_i) (``mi.Color3f`` each, no cosine).

    ``n``, ``wo``, ``wi``: unit world-space vectors; ``wo`` points towards the viewer,
    ``wi`` towards the light. Both parts are 0 when n·ω_o ≤ 0 or n·ω_i ≤ 0.
    """
    albedo = mi.Color3f(albedo)
    cos_o, cos_i = dr.dot(n, wo), dr.dot(n, wi)
    valid = (cos_o > 0.0) & (cos_i > 0.0)
    co, ci = dr.maximum(cos_o, _COS_EPS), dr.maximum(cos_i, _COS_EPS)
    # Half vector without normalising (wo + wi): |wo + wi| = 2 cos_d, cos_d = wo·h = wi·h.
    cos_d = dr.sqrt(dr.maximum(0.5 + 0.5 * dr.dot(wo, wi), 0.0))
    cos_h = (co + ci) / dr.maximum(2.0 * cos_d, _COS_EPS)           # n·h
    cos_h = dr.minimum(cos_h, 1.0)
    alpha = ggx_alpha(roughness)
    f0 = 0.04 * (1.0 - metallic) + albedo * metallic
    F = fresnel_schlick(f0, cos_d)
    vis = 0.5 / (ci * _smith_s(alpha, co) + co * _smith_s(alpha, ci))  # G2/(4 co ci)
    spec = F * (ggx_d(alpha, cos_h) * vis)
    diff = albedo * ((1.0 - metallic) / dr.pi)
    zero = mi.Color3f(0.0)
    return dr.select(valid, diff, zero), dr.select(valid, spec, zero)


def eval_brdf(albedo, roughness, metallic, n, wo, wi):
    """f(ω_o, ω_i) = diffuse + specular (``mi.Color3f``, WITHOUT the cosine factor)."""
    d, s = eval_brdf_split(albedo, roughness, metallic, n, wo, wi)
    return d + s


# ---------------------------------------------------------------------------------------
# Frames

def frame_from_normal(n):
    """Orthonormal tangents (s, t) with (s, t, n) right-handed, branchless construction of
    Duff et al. 2017 ("Building an orthonormal basis, revisited"); matches
    ``mi.coordinate_system``."""
    sign = dr.copysign(1.0, n.z)
    a = -1.0 / (sign + n.z)
    b = n.x * n.y * a
    s = mi.Vector3f(dr.fma(sign * n.x * n.x, a, 1.0), sign * b, -sign * n.x)
    t = mi.Vector3f(b, dr.fma(n.y * n.y, a, sign), -n.y)
    return s, t


def to_local(n, v):
    """World vector → local frame (z = n)."""
    s, t = frame_from_normal(n)
    return mi.Vector3f(dr.dot(v, s), dr.dot(v, t), dr.dot(v, n))


def to_world(n, v):
    """Local vector (z = n) → world frame."""
    s, t = frame_from_normal(n)
    return s * v.x + t * v.y + n * v.z


# ---------------------------------------------------------------------------------------
# Samplers: u ∈ [0,1)² → local direction + solid-angle pdf

_ONE_MINUS = float(np.nextafter(np.float32(1.0), np.float32(0.0)))   # largest f32 < 1


def _clamp_u(u):
    """Clamp u to [0, 1−2⁻²⁴]: a float64 value < 1 may round to 1.0 in float32."""
    return mi.Point2f(dr.clip(u.x, 0.0, _ONE_MINUS), dr.clip(u.y, 0.0, _ONE_MINUS))


def sample_uniform_hemisphere(u):
    """Uniform on the upper hemisphere, pdf = 1/2π. z = 1 − u.x ∈ (0, 1]."""
    u = _clamp_u(u)
    z = 1.0 - u.x
    r = dr.sqrt(dr.maximum(1.0 - z * z, 0.0))
    sp, cp = dr.sincos(dr.two_pi * u.y)
    return mi.Vector3f(r * cp, r * sp, z), dr.full(mi.Float, dr.inv_two_pi, dr.width(u))


def pdf_uniform_hemisphere(w):
    return dr.select(w.z > 0.0, dr.inv_two_pi, 0.0)


def sample_cosine_hemisphere(u):
    """Cosine-weighted (Malley, polar map), pdf = cos θ / π. z = √(1 − u.x) ∈ (0, 1]."""
    u = _clamp_u(u)
    r = dr.sqrt(u.x)
    z = dr.sqrt(dr.maximum(1.0 - u.x, 0.0))
    sp, cp = dr.sincos(dr.two_pi * u.y)
    return mi.Vector3f(r * cp, r * sp, z), z * dr.inv_pi


def pdf_cosine_hemisphere(w):
    return dr.maximum(w.z, 0.0) * dr.inv_pi


def sample_ggx_vndf(u, wo, alpha):
    """GGX visible-normal sampling (Heitz 2018, "Sampling the GGX distribution of visible
    normals"), isotropic α. Returns (ω_i, pdf) with ω_i = reflect(ω_o, h) and
    pdf = D_v(h)/(4 ω_o·h) = G1(ω_o) D(h) / (4 cos_o). The pdf is 0 (an invalid sample)
    when ω_i falls below the horizon or cos_o ≤ 0; the returned direction is then
    still finite but must be discarded (the contribution f·cos/pdf is taken as 0)."""
    u = _clamp_u(u)
    # Stretch ω_o to the hemisphere configuration (α = 1); ω_o = −n (nothing left after the
    # clamp) would normalise a zero vector into NaN: any finite direction does (pdf is 0)
    v = mi.Vector3f(alpha * wo.x, alpha * wo.y, dr.maximum(wo.z, 0.0))
    v2 = dr.squared_norm(v)
    vh = dr.select(v2 > 1e-30, v * dr.rsqrt(dr.maximum(v2, 1e-30)), mi.Vector3f(0.0, 0.0, 1.0))
    lensq = vh.x * vh.x + vh.y * vh.y
    inv_len = dr.rsqrt(dr.maximum(lensq, 1e-20))
    t1 = dr.select(lensq > 1e-14, mi.Vector3f(-vh.y * inv_len, vh.x * inv_len, 0.0),
                   mi.Vector3f(1.0, 0.0, 0.0))
    t2 = dr.cross(vh, t1)
    # Uniform disk point, warped towards the projected visible hemisphere
    r = dr.sqrt(u.x)
    sp, cp = dr.sincos(dr.two_pi * u.y)
    p1, p2 = r * cp, r * sp
    s = 0.5 * (1.0 + vh.z)
    p2 = (1.0 - s) * dr.sqrt(dr.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    nh = t1 * p1 + t2 * p2 + vh * dr.sqrt(dr.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    # Unstretch back to the α ellipsoid
    h = dr.normalize(mi.Vector3f(alpha * nh.x, alpha * nh.y, dr.maximum(nh.z, 0.0)))
    wi = 2.0 * dr.dot(wo, h) * h - wo
    return wi, pdf_ggx_vndf(wo, wi, alpha)


def pdf_ggx_vndf(wo, wi, alpha):
    """Solid-angle pdf of :func:`sample_ggx_vndf` (0 for wi.z ≤ 0 or wo.z ≤ 0)."""
    co = dr.maximum(wo.z, 0.0)
    cos_d = dr.sqrt(dr.maximum(0.5 + 0.5 * dr.dot(wo, wi), 0.0))          # ω_o·h
    cos_h = dr.minimum((co + dr.maximum(wi.z, 0.0)) / dr.maximum(2.0 * cos_d, _COS_EPS), 1.0)
    pdf = ggx_d(alpha, cos_h) * 0.5 / (co + _smith_s(alpha, co))          # G1 D / (4 co)
    return dr.select((wo.z > 0.0) & (wi.z > 0.0) & (cos_d > 0.0), pdf, 0.0)


# ---------------------------------------------------------------------------------------
# Low-discrepancy point sets (numpy, host side)

def _radical_inverse_base2(i: np.ndarray) -> np.ndarray:
    """Van der Corput radical inverse in base 2 of uint32 indices, as float64."""
    v = i.astype(np.uint32)
    v = ((v << 16) | (v >> 16)).astype(np.uint32)
    v = (((v & 0x00FF00FF) << 8) | ((v & 0xFF00FF00) >> 8)).astype(np.uint32)
    v = (((v & 0x0F0F0F0F) << 4) | ((v & 0xF0F0F0F0) >> 4)).astype(np.uint32)
    v = (((v & 0x33333333) << 2) | ((v & 0xCCCCCCCC) >> 2)).astype(np.uint32)
    v = (((v & 0x55555555) << 1) | ((v & 0xAAAAAAAA) >> 1)).astype(np.uint32)
    return v.astype(np.float64) * 2.0 ** -32


def hammersley(n: int) -> np.ndarray:
    """[n, 2] Hammersley set (i/n, radical_inverse_2(i)), float64 in [0, 1)."""
    if n < 1:
        raise ValueError(f"hammersley(n): n must be ≥ 1, got {n}")
    i = np.arange(n, dtype=np.uint64)
    return np.stack([i.astype(np.float64) / n, _radical_inverse_base2(i)], axis=1)  # [n, 2]


def rotated_hammersley(n: int, seed) -> np.ndarray:
    """[n, 2] Hammersley set with a Cranley–Patterson rotation (u + δ) mod 1, δ drawn from
    ``np.random.default_rng(seed)`` (re-randomised per iteration in the paper). Values are
    clamped to the largest float32 below 1 so that a float32 cast stays in [0, 1)."""
    offset = np.random.default_rng(seed).random(2)                                 # [2]
    u = np.mod(hammersley(n) + offset[None, :], 1.0)                               # [n, 2]
    return np.minimum(u, _ONE_MINUS)
