"""Lighting-estimation metrics: the array-of-spheres protocol, in pure NumPy.

Paper, Appendix "Details of Lighting Estimation", Ablations: estimated HDR environment maps
are compared through renders of spheres lit by them ("array of spheres", Gardner et al.
2017/2019; materials and metrics as in DiffusionLight, Phongthawee et al. 2024):
a **mirror**, a **matte silver** and a **diffuse** sphere, scored with scale-invariant RMSE,
RGB angular error and normalised RMSE over the sphere pixels.

**Maps.** Linear [H, W, 3] equirect, Blender Z-up (``lighting.envmap``):
u = 0.5 − atan2(y, x)/2π, v = acos(z)/π, v = 0 the top row. ``area_resize_equirect``
resamples by exact solid-angle-weighted area averaging (Σ L dω is preserved).

**Camera.** Orthographic view of a unit sphere, S×S pixels (pixel centres inside the unit disc
form the mask). Azimuth a = 0 puts the camera on the −Y axis looking along +Y, image right
= +X, image up = +Z; azimuth a rotates the camera by a about +Z (counter-clockwise seen from
above), i.e. toward-camera c = (sin a, −cos a, 0), right = (cos a, sin a, 0). A mirror
sphere's centre pixel reflects c (behind the viewer). ``ARRAY_AZIMUTHS`` (0°, 90°, 180°,
270°) give 4 views that together see the whole map.

**Materials** (``MATERIALS``):

* ``mirror``: perfect specular, reflectance 1: L(r), r = 2(n·c)n − c, bilinear lookup
  (wraps in u) of the map at its own resolution.
* ``matte_silver``: metallic 1, roughness 0.35, F0 = albedo = ``SILVER_F0``, the specular
  lobe of the project's simplified Disney BRDF (``shading.brdf``: GGX D with
  α = max(r², 1e-3), height-correlated Smith, Schlick Fresnel with ω_o·h).
* ``diffuse``: Lambert, albedo 0.8.

Glossy and diffuse renders are **deterministic quadratures** over the pixels of the map
area-downsampled to (q, 2q) (``quad_height``, default 32), with exact pixel solid angles
(``hdr.pixel_solid_angles``); each row of the quadrature is rescaled so that a constant map
is rendered exactly: the diffuse row sums Σ cos⁺ dω to π, the glossy rows (Schlick split:
F = F0·1 + (1 − F0)·(1 − ω_o·h)⁵, two scalar operators) to the directional albedo terms
computed once by 2048-point Hammersley quadrature with GGX visible-normal sampling. The
operator depends on the sphere and the grid only, so it is built once (cached) for the
azimuth-0 camera; other azimuths that are multiples of 360°/2q rotate the map by whole
columns instead (exact), any other azimuth builds its own operator.

**Metrics** (on the masked pixels of all views, float64, any common scale; NaN/Inf, shape
mismatch or an empty mask raise ValueError):

* ``si_rmse`` = min_α RMSE(α·est, gt) over one scalar α for all channels (Grosse et al. 2009,
  as in Gardner 2019 / StyleLight / DiffusionLight): α* = Σ est·gt / Σ est².
* ``angular_error_deg``: mean angle between per-pixel RGB vectors, degrees; both zero → 0°,
  exactly one zero → 90° (the largest angle between non-negative colours).
* ``nrmse`` = RMSE(est, gt) / RMS(gt) (the StyleLight code instead normalises each render
  by its 0.01/99.9 percentiles before an RMSE; ours is scale-aware and needs no tonemap).
"""
from __future__ import annotations

from functools import lru_cache
from math import pi

import numpy as np

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.equirect import (
    equirect_dir_to_uv_np,
    equirect_directions,
    pixel_solid_angles,
    sample_equirect_np,
)
from comgs_dr.lighting.hdr import area_resize_equirect
from comgs_dr.shading.brdf import ALPHA_MIN, hammersley

__all__ = ["MATERIALS", "ARRAY_AZIMUTHS", "SILVER_F0", "SILVER_ROUGHNESS", "DIFFUSE_ALBEDO",
           "area_resize_equirect", "sphere_geometry", "render_sphere", "render_spheres",
           "ggx_specular_np", "specular_albedo_terms", "si_rmse", "angular_error_deg",
           "nrmse", "sphere_metrics"]

MATERIALS = ("mirror", "matte_silver", "diffuse")
ARRAY_AZIMUTHS = (0.0, 90.0, 180.0, 270.0)
SILVER_F0 = np.array([0.95, 0.93, 0.88])     # metallic 1: F0 = albedo (silver-ish grey)
SILVER_ROUGHNESS = 0.35
DIFFUSE_ALBEDO = 0.8
_COS_EPS = 1e-12


# ---------------------------------------------------------------------------------------
# Maps

def _check_map(env, name: str) -> np.ndarray:
    env = np.asarray(env)
    if env.ndim != 3 or env.shape[-1] < 3 or env.shape[1] < 2:
        raise ValueError(f"{name}: expected an [H, W, 3] equirect map, got shape {env.shape}")
    env = env[..., :3].astype(np.float64)
    if not np.isfinite(env).all():
        raise ValueError(f"{name}: map has {int((~np.isfinite(env)).sum())} NaN/Inf values")
    return env


# ---------------------------------------------------------------------------------------
# Sphere geometry

def _camera(azimuth_deg: float):
    a = np.radians(float(azimuth_deg))
    c = np.array([np.sin(a), -np.cos(a), 0.0])          # towards the camera
    right = np.array([np.cos(a), np.sin(a), 0.0])
    return c, right, np.array([0.0, 0.0, 1.0])


def sphere_geometry(size: int = 64, azimuth_deg: float = 0.0):
    """Orthographic unit sphere: (normals [S, S, 3] world, 0 outside; toward-camera c [3];
    mask [S, S] bool). Row 0 is the top of the image (+Z)."""
    if int(size) != size or size < 2:
        raise ValueError(f"sphere_geometry: size must be an integer >= 2, got {size}")
    size = int(size)
    t = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    sx, sy = np.meshgrid(t, -t)                          # [S, S] image x right, y up
    r2 = sx * sx + sy * sy
    mask = r2 < 1.0
    sz = np.sqrt(np.maximum(1.0 - r2, 0.0))
    c, right, up = _camera(azimuth_deg)
    n = sx[..., None] * right + sy[..., None] * up + sz[..., None] * c
    return np.where(mask[..., None], n, 0.0), c, mask


# ---------------------------------------------------------------------------------------
# BRDF (NumPy copy of shading.brdf's specular lobe)

def _smith_s(alpha, cos):
    a2 = alpha * alpha
    return np.sqrt(np.maximum(cos * cos * (1.0 - a2) + a2, 0.0))


def ggx_specular_np(roughness: float, cos_o, cos_i, cos_d, cos_h):
    """(D·G2/(4 cos_o cos_i), (1 − cos_d)⁵) of ``shading.brdf.eval_brdf_split``'s specular
    lobe, so that f_spec = (F0·a + (1 − F0)·a·b) with a, b the two returned arrays; cos_d =
    ω_o·h, cos_h = n·h. Zero where cos_o ≤ 0 or cos_i ≤ 0."""
    alpha = max(float(roughness) ** 2, ALPHA_MIN)
    co, ci = np.maximum(cos_o, _COS_EPS), np.maximum(cos_i, _COS_EPS)
    a2 = alpha * alpha
    ch = np.clip(cos_h, 0.0, 1.0)
    t = ch * ch * (a2 - 1.0) + 1.0
    d = np.where(cos_h > 0.0, a2 / (pi * t * t), 0.0)
    vis = 0.5 / (ci * _smith_s(alpha, co) + co * _smith_s(alpha, ci))
    x = 1.0 - np.clip(cos_d, 0.0, 1.0)
    valid = (cos_o > 0.0) & (cos_i > 0.0)
    return np.where(valid, d * vis, 0.0), x ** 5


@lru_cache(maxsize=8)
def specular_albedo_terms(roughness: float, n_mu: int = 256, n_samples: int = 2048):
    """Directional albedo terms of the GGX lobe, tabulated at μ_o = (i + 0.5)/n_mu:
    (mu [n_mu], A [n_mu], B [n_mu]) with ∫ f_spec cos_i dω_i = F0·A + (1 − F0)·B,
    A = ∫ D G2/(4 cos_o) dω, B = ∫ (1 − ω_o·h)⁵ D G2/(4 cos_o) dω. Hammersley points through
    GGX visible-normal sampling (Heitz 2018): weight G2/G1(ω_o), bounded by 1."""
    alpha = max(float(roughness) ** 2, ALPHA_MIN)
    mu = (np.arange(n_mu) + 0.5) / n_mu                                       # [M]
    u = hammersley(n_samples)                                                 # [N, 2]
    wo = np.stack([np.sqrt(1 - mu * mu), np.zeros_like(mu), mu], -1)[:, None]  # [M, 1, 3]
    vh = wo * np.array([alpha, alpha, 1.0])
    vh = vh / np.linalg.norm(vh, axis=-1, keepdims=True)
    lensq = vh[..., 0] ** 2 + vh[..., 1] ** 2
    inv = 1.0 / np.sqrt(np.maximum(lensq, 1e-20))
    t1 = np.stack([-vh[..., 1] * inv, vh[..., 0] * inv, np.zeros_like(inv)], -1)
    t2 = np.cross(vh, t1)
    r, ph = np.sqrt(u[:, 0]), 2 * pi * u[:, 1]
    p1, p2 = r * np.cos(ph), r * np.sin(ph)                                   # [N]
    s = 0.5 * (1.0 + vh[..., 2])                                              # [M, 1]
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * p2         # [M, N]
    p1 = np.broadcast_to(p1, p2.shape)
    nh = (t1 * p1[..., None] + t2 * p2[..., None]
          + vh * np.sqrt(np.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))[..., None])
    h = nh * np.array([alpha, alpha, 1.0])
    h[..., 2] = np.maximum(h[..., 2], 0.0)
    h /= np.linalg.norm(h, axis=-1, keepdims=True)                            # [M, N, 3]
    cos_d = (wo * h).sum(-1)                                                  # ω_o·h
    cos_i = 2.0 * cos_d * h[..., 2] - mu[:, None]                             # (reflect).z
    ci = np.maximum(cos_i, _COS_EPS)
    co = mu[:, None]
    g2_over_g1 = (co + _smith_s(alpha, co)) * ci / (ci * _smith_s(alpha, co)
                                                    + co * _smith_s(alpha, ci))
    wgt = np.where(cos_i > 0.0, g2_over_g1, 0.0)
    a = wgt.mean(1)
    b = (wgt * (1.0 - np.clip(cos_d, 0.0, 1.0)) ** 5).mean(1)
    return mu, a, b


# ---------------------------------------------------------------------------------------
# Quadrature operators

@lru_cache(maxsize=6)
def _operators(material: str, size: int, azimuth_deg: float, qh: int):
    """Row-normalised quadrature operators for the sphere pixels: a tuple of [P, D] float64
    arrays (diffuse: one; matte silver: A-term and B-term), with P masked pixels and D = 2q²
    quadrature directions of the (q, 2q) grid."""
    n, c, mask = sphere_geometry(size, azimuth_deg)
    n = n[mask]                                                               # [P, 3]
    dirs = equirect_directions(qh, 2 * qh).reshape(-1, 3)                     # [D, 3]
    dw = np.broadcast_to(pixel_solid_angles(qh, 2 * qh), (qh, 2 * qh)).ravel()  # [D]
    cos_i = n @ dirs.T                                                        # [P, D]
    if material == "diffuse":
        k = np.maximum(cos_i, 0.0) * dw
        k /= np.maximum(k.sum(1, keepdims=True), 1e-300)                      # rows -> 1
        return (k,)
    cos_o = n @ c                                                             # [P]
    cos_d = np.sqrt(np.maximum(0.5 + 0.5 * (dirs @ c), 0.0))[None, :]         # [1, D]
    cos_h = np.minimum((np.maximum(cos_o, _COS_EPS)[:, None] + np.maximum(cos_i, _COS_EPS))
                       / np.maximum(2.0 * cos_d, _COS_EPS), 1.0)
    lobe, schlick = ggx_specular_np(SILVER_ROUGHNESS, cos_o[:, None], cos_i, cos_d, cos_h)
    ka = lobe * np.maximum(cos_i, 0.0) * dw                                   # [P, D]
    kb = ka * schlick
    mu, ta, tb = specular_albedo_terms(SILVER_ROUGHNESS)
    m = np.clip(cos_o, mu[0], mu[-1])
    ka *= (np.interp(m, mu, ta) / np.maximum(ka.sum(1), 1e-300))[:, None]
    kb *= (np.interp(m, mu, tb) / np.maximum(kb.sum(1), 1e-300))[:, None]
    return ka, kb


def _apply(material: str, ops, q: np.ndarray) -> np.ndarray:
    """Radiance [P, 3k] of the sphere pixels from k flattened quadrature maps q [D, 3k]."""
    if material == "diffuse":
        return DIFFUSE_ALBEDO * (ops[0] @ q)
    f0 = np.tile(SILVER_F0, q.shape[1] // 3)
    return f0 * (ops[0] @ q) + (1.0 - f0) * (ops[1] @ q)


def render_sphere(env, material: str = "diffuse", size: int = 64,
                  azimuths=(0.0,), quad_height: int = 32):
    """Render one material under a linear equirect map ``env`` [H, W, 3] from the given
    camera azimuths (degrees). Returns (images [V, S, S, 3] float64, 0 outside; mask
    [S, S] bool)."""
    if material not in MATERIALS:
        raise ValueError(f"render_sphere: material must be one of {MATERIALS}, got "
                         f"{material!r}")
    env = _check_map(env, "render_sphere")
    azimuths = [float(a) for a in np.atleast_1d(azimuths)]
    if not azimuths:
        raise ValueError("render_sphere: azimuths is empty")
    size = int(size)
    _, _, mask = sphere_geometry(size)
    out = np.zeros((len(azimuths), size, size, 3))
    if material == "mirror":
        for i, a in enumerate(azimuths):
            n, c, _ = sphere_geometry(size, a)
            nm = n[mask]                                                      # [P, 3]
            r = 2.0 * (nm @ c)[:, None] * nm - c
            out[i][mask] = sample_equirect_np(env, equirect_dir_to_uv_np(r))
        return out, mask
    qh = int(quad_height)
    if qh < 2:
        raise ValueError(f"render_sphere: quad_height must be >= 2, got {quad_height}")
    qmap = area_resize_equirect(env, qh, 2 * qh)                              # [q, 2q, 3]
    rolled, direct = [], []
    for i, a in enumerate(azimuths):
        shift = a / 360.0 * 2 * qh                 # rotating the camera by a = rolling the map
        if abs(shift - round(shift)) < 1e-9:
            rolled.append((i, np.roll(qmap, int(round(shift)), axis=1).reshape(-1, 3)))
        else:
            direct.append((i, a))
    if rolled:                                     # one matmul for all rolled views
        q = np.concatenate([r for _, r in rolled], 1)                         # [D, 3V]
        res = _apply(material, _operators(material, size, 0.0, qh), q)        # [P, 3V]
        for k, (i, _) in enumerate(rolled):
            out[i][mask] = res[:, 3 * k:3 * k + 3]
    for i, a in direct:
        out[i][mask] = _apply(material, _operators(material, size, a % 360.0, qh),
                              qmap.reshape(-1, 3))
    return out, mask


def render_spheres(env, materials=MATERIALS, size: int = 64, azimuths=ARRAY_AZIMUTHS,
                   quad_height: int = 32) -> tuple[dict, np.ndarray]:
    """The array of spheres: ({material: [V, S, S, 3]}, mask [S, S])."""
    out, mask = {}, None
    for m in materials:
        out[m], mask = render_sphere(env, m, size, azimuths, quad_height)
    return out, mask


# ---------------------------------------------------------------------------------------
# Metrics

def _prep_pair(est, gt, mask, name: str):
    """Masked [N, C] float64 arrays (validated)."""
    est, gt = np.asarray(est, np.float64), np.asarray(gt, np.float64)
    if est.shape != gt.shape or est.ndim < 2:
        raise ValueError(f"{name}: est and gt must have the same [..., C] shape, got "
                         f"{est.shape} and {gt.shape}")
    for label, a in (("est", est), ("gt", gt)):
        bad = int((~np.isfinite(a)).sum())
        if bad:
            raise ValueError(f"{name}: {label} has {bad} NaN/Inf values")
    if mask is None:
        m = np.ones(est.shape[:-1], bool)
    else:
        mask = np.asarray(mask)
        if np.issubdtype(mask.dtype, np.floating) and not np.isfinite(mask).all():
            raise ValueError(f"{name}: mask has NaN/Inf values")
        try:
            m = np.broadcast_to(mask > 0.5 if mask.dtype != bool else mask, est.shape[:-1])
        except ValueError:
            raise ValueError(f"{name}: mask shape {mask.shape} does not match the pixel "
                             f"shape {est.shape[:-1]}") from None
    if not m.any():
        raise ValueError(f"{name}: the mask selects no pixel")
    return est[m], gt[m]


def _scale(a) -> float:
    s = float(np.abs(a).max()) if a.size else 0.0
    return s if s > 0.0 else 1.0


def si_rmse(est, gt, mask=None) -> float:
    """Scale-invariant RMSE: min over one scalar α of RMSE(α·est, gt) over the masked pixels
    and all channels, α* = Σ est·gt / Σ est² (α = 0 when est is all zero). Computed on
    max-normalised copies, so any finite magnitude (1e6 suns) is safe."""
    e, g = _prep_pair(est, gt, mask, "si_rmse")
    se, sg = _scale(e), _scale(g)
    e, g = e / se, g / sg
    ee = float((e * e).sum())
    alpha = float((e * g).sum()) / ee if ee > 0.0 else 0.0
    return float(np.sqrt(np.mean((alpha * e - g) ** 2)) * sg)


def angular_error_deg(est, gt, mask=None) -> float:
    """Mean angle (degrees) between the RGB vectors of est and gt per masked pixel;
    0° where both are zero, 90° where exactly one is zero."""
    e, g = _prep_pair(est, gt, mask, "angular_error_deg")
    e = e / _scale(e)
    g = g / _scale(g)
    ne, ng = np.linalg.norm(e, axis=-1), np.linalg.norm(g, axis=-1)
    ok = (ne > 0) & (ng > 0)
    cos = np.where(ok, (e * g).sum(-1) / np.where(ok, ne * ng, 1.0), 0.0)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    ang = np.where(ok, ang, np.where((ne > 0) | (ng > 0), 90.0, 0.0))
    return float(ang.mean())


def nrmse(est, gt, mask=None) -> float:
    """RMSE(est, gt) / RMS(gt) over the masked pixels (inf if gt is all zero and est is not,
    0 if both are)."""
    e, g = _prep_pair(est, gt, mask, "nrmse")
    s = max(_scale(e), _scale(g))
    e, g = e / s, g / s
    num, den = float(np.sqrt(np.mean((e - g) ** 2))), float(np.sqrt(np.mean(g * g)))
    if den == 0.0:
        return 0.0 if num == 0.0 else float("inf")
    return num / den


def sphere_metrics(est_renders: dict, gt_renders: dict, mask) -> dict:
    """{material: {"si_rmse", "angular_deg", "nrmse"}} for renders of ``render_spheres``."""
    out = {}
    for m, gt in gt_renders.items():
        est = est_renders[m]
        out[m] = {"si_rmse": si_rmse(est, gt, mask),
                  "angular_deg": angular_error_deg(est, gt, mask), "nrmse": nrmse(est, gt, mask)}
    return out


# ---------------------------------------------------------------------------------------
# One estimated map against the true one (the demo, reports)

def irradiance(env, normal) -> float:
    """Luminance irradiance E(n) = Σ L(ω) max(0, n·ω) dω of a linear equirect map."""
    env = _check_map(env, "irradiance")
    h, w = env.shape[:2]
    cos = np.clip(equirect_directions(h, w) @ np.asarray(normal, np.float64), 0.0, None)
    lum = env @ LUMA
    return float((lum * cos * pixel_solid_angles(h, w)).sum())


def irradiance_contrast(env, normals: int = 200) -> float:
    """max / min of the luminance irradiance of a linear equirect map over ``normals``
    near-uniform directions (a Fibonacci sphere): 1 for a flat light; how much the light's
    direction shades an object (a studio's key light: 13.7 for ``blender_studio``)."""
    env = _check_map(env, "irradiance_contrast")
    h, w = env.shape[:2]
    i = np.arange(normals) + 0.5
    z, phi = 1.0 - 2.0 * i / normals, np.pi * (1.0 + 5 ** 0.5) * i
    r = np.sqrt(1.0 - z ** 2)
    n = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    power = ((env @ LUMA) * pixel_solid_angles(h, w)).reshape(-1)
    e = np.maximum(n @ equirect_directions(h, w).reshape(-1, 3).T, 0.0) @ power
    return float(e.max() / max(e.min(), 1e-12))


def at_coarser(est, gt) -> tuple:
    """(est, gt) equirect maps with the finer one area-averaged to the coarser one's size, as
    ``compare-light`` compares and shows them (a coarse truth is not upsampled)."""
    if est.shape[0] < gt.shape[0]:
        gt = area_resize_equirect(gt, *est.shape[:2])
    elif est.shape[0] > gt.shape[0]:
        est = area_resize_equirect(est, *gt.shape[:2])
    return est, gt


def compare_maps(est, gt, size: int = 48) -> dict:
    """Scores of an estimated map against the true one (both linear equirect; ``est`` is
    area-resampled to ``gt``'s size): array-of-spheres si-RMSE / angular error (diffuse and
    matte silver), the angle between the dominant lights (``hdr.extract_lights``), and the
    irradiance ratio E(facing the true dominant light) / E(facing up) of each map. The two
    dominant directions are returned (``true_light_direction``, ``est_light_direction``):
    they are extracted at ``gt``'s size, so with a coarse truth they can differ from the
    lights ``estimate-light`` lists at the estimate's own size.
    ValueError for an all-zero true map."""
    from comgs_dr.lighting.hdr import extract_lights
    gt = _check_map(gt, "compare_maps gt")
    if not (gt > 0).any():          # relative scores (nrmse, ratios) are undefined: not inf
        raise ValueError("compare_maps: the true map is all zero (no light to compare with)")
    est = area_resize_equirect(_check_map(est, "compare_maps est"), *gt.shape[:2])
    mats = ("diffuse", "matte_silver")
    r_est, mask = render_spheres(est, mats, size)
    r_gt, _ = render_spheres(gt, mats, size)
    out = {"spheres": sphere_metrics(r_est, r_gt, mask)}
    le, lg = extract_lights(est, k=1), extract_lights(gt, k=1)
    if lg:
        d = lg[0]["direction"]
        out["true_light_direction"] = [float(x) for x in d]
        if le:
            out["est_light_direction"] = [float(x) for x in le[0]["direction"]]
            out["light_angle_deg"] = float(np.degrees(np.arccos(np.clip(
                float(le[0]["direction"] @ d), -1.0, 1.0))))
        up = np.array([0.0, 0.0, 1.0])
        for name, m in (("est", est), ("gt", gt)):
            e_up = irradiance(m, up)
            out[f"light_up_irradiance_ratio_{name}"] = irradiance(m, d) / e_up if e_up > 0 else None
    dw = pixel_solid_angles(*gt.shape[:2])[..., None]
    out["power_ratio_est_gt"] = float((est * dw).sum() / max(float((gt * dw).sum()), 1e-300))
    return out
