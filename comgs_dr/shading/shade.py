"""Deferred physically based shading of G-buffer points (paper eqs. render_equation,
illumination, knn).

For each shading point x (normal n, view direction ω_o, albedo a, roughness r, metallic m)
and S_r directions ω_i:

    C_pbr(x) = 1/S_r · Σ_i f(ω_o, ω_i) · L_i(ω_i) · (ω_i·n) / pdf(ω_i),
    L_i(ω) = (1 − O(ω)) · L_dir(ω) + L_in(ω).

Estimators (``ShadingConfig.sampling``):

* ``'mis'`` (rendering default): half of the S_r directions are drawn from the environment
  map (∝ luminance × solid angle, exact octahedral pdf), half from the BRDF (a cosine lobe
  for the diffuse part, GGX visible normals for the specular part, chosen per sample by the
  specular share); every direction is weighted by the balance heuristic, i.e. divided by
  the mixture pdf ½·p_env + ½·p_brdf. Suns and glossy lobes are both sampled where they
  matter, so neither gives fireflies.
* ``'uniform'`` (the paper's training estimator, 2π/S_r) and ``'cosine'``: cheaper, kept for
  step 2's training where the map starts constant; their variance grows like 1/α² for
  small roughness, so :attr:`ShadingConfig.min_roughness` should clamp r there.

Sample sets: a Hammersley set per strategy, rotated per shading point by a random
Cranley–Patterson offset drawn from (seed, point index) when ``decorrelate`` (default), so
neighbouring pixels use different directions (noise, not structured error); the tangent
frame is then immaterial (the rotation randomises the azimuth), which removes the seam of a
shared set at horizontal normals. L_dir is the octahedral environment map (anything with
``eval_world(d, data)`` / ``sample_world(u)`` / ``pdf_world(d)``: ``OctEnvmap`` or the
``octenvmap`` emitter); O and L_in come from a *visibility source*
(:mod:`comgs_dr.shading.visibility`).

All (point, direction) pairs form one wide array (never a Python loop over
directions: one kernel per shading call), and each source can skip the indirect term (``indirect=False``).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit
from comgs_dr.shading import brdf


SAMPLINGS = ("mis", "uniform", "cosine")
SPEC_SHARE = (0.1, 0.9)      # clamp of the probability of sampling the GGX lobe (BRDF strategy)


@dataclass(frozen=True)
class ShadingConfig:
    rays: int = 128                  # S_r (sec. 4.1: 128 in training, 256 for rendering)
    sampling: str = "uniform"        # 'mis' (rendering) | 'uniform' (paper) | 'cosine'
    indirect: bool = True            # add L_in (inter-reflections)
    occlusion: bool = True           # apply (1 − O) to the environment light
    decorrelate: bool = True         # a random rotation of the sample set per point
    min_roughness: float = 0.0       # r is clamped to this at shading time

    def __post_init__(self):
        if self.rays < 1:
            raise ValueError(f"ShadingConfig: rays must be ≥ 1, got {self.rays}")
        if self.sampling not in SAMPLINGS:
            raise ValueError(f"ShadingConfig: sampling must be one of {', '.join(SAMPLINGS)}, "
                             f"got {self.sampling!r}")
        if self.sampling == "mis" and self.rays < 2:
            raise ValueError("ShadingConfig: 'mis' needs rays ≥ 2 (half per strategy)")
        if not 0.0 <= self.min_roughness <= 1.0:
            raise ValueError(f"ShadingConfig: min_roughness must be in [0, 1], got {self.min_roughness}")


@dataclass
class ShadingPoints:
    """Per-point inputs [N]; ``albedo``/``roughness``/``metallic`` may carry gradients."""
    position: mi.Point3f
    normal: mi.Vector3f          # unit
    wo: mi.Vector3f              # unit, towards the viewer
    albedo: mi.Color3f
    roughness: mi.Float
    metallic: mi.Float

    @property
    def count(self) -> int:
        return dr.width(self.position)


# ---------------------------------------------------------------------------------------
# Visibility sources: (point index [M], world direction [M]) -> (O [M], L_in [M])







# ---------------------------------------------------------------------------------------

def direction_set(rays: int, seed: int) -> np.ndarray:
    """[S, 2] rotated Hammersley points (a fresh random rotation per seed/iteration)."""
    return brdf.rotated_hammersley(rays, seed)


def _point_offsets(n_pts: int, seed: int, dims: int):
    """Per-point Cranley–Patterson offsets in [0, 1)^dims (PCG32 stream per point)."""
    # the seed is opaque: as a literal it would recompile the kernels for every seed
    state = dr.opaque(mi.UInt64, (int(seed) * 0x9E3779B9 + 0x5851F42D) % (1 << 64))
    rng = mi.PCG32(n_pts, initstate=state, initseq=dr.arange(mi.UInt64, n_pts))
    return [rng.next_float32() for _ in range(dims)]


def sample_points(n_pts: int, s: int, seed: int, decorrelate: bool, blocks=None):
    """(point id [N*S], sample id [N*S], u [N*S] Point2f, u_lobe [N*S]) for S directions per
    point: one Hammersley set per block of ``blocks`` (sizes summing to S; MIS uses one
    block per strategy), rotated per point (``decorrelate``) or per call."""
    idx = dr.arange(mi.UInt32, n_pts * s)
    pid, sid = idx // s, idx % s                                           # [N*S]
    blocks = blocks or [s]
    base = np.concatenate([brdf.hammersley(b) for b in blocks]).astype(np.float32)   # [S, 2]
    lobe = np.concatenate([(np.arange(b) * 0.6180339887498949) % 1.0
                           for b in blocks]).astype(np.float32)           # [S] golden ratio
    uu = dr.gather(mi.Point2f, to_jit(mi.Point2f, base.T), sid)
    ul = dr.gather(mi.Float, to_jit(mi.Float, lobe), sid)
    if decorrelate:
        off = _point_offsets(n_pts, seed, 3)
        ox, oy, ol = (dr.gather(mi.Float, o, pid) for o in off)
    else:
        o = np.random.default_rng(seed).random(3).astype(np.float32)
        ox, oy, ol = (dr.opaque(mi.Float, float(v)) for v in o)
    frac = lambda x: x - dr.floor(x)                                       # noqa: E731
    one = brdf._ONE_MINUS
    u = mi.Point2f(dr.minimum(frac(uu.x + ox), one), dr.minimum(frac(uu.y + oy), one))
    return pid, sid, u, dr.minimum(frac(ul + ol), one)


def _spec_share(a, m, cos_o):
    """Probability of drawing the GGX lobe in BRDF sampling: the Fresnel-weighted specular
    share of the two lobes' albedos (clamped to SPEC_SHARE)."""
    f0 = 0.04 * (1.0 - m) + a * m
    spec = mi.luminance(brdf.fresnel_schlick(f0, cos_o))
    diff = mi.luminance(a * (1.0 - m))
    return dr.clip(spec / dr.maximum(spec + diff, 1e-6), *SPEC_SHARE)


def _brdf_pdf(local_wo, local_wi, alpha, ks):
    """Solid-angle pdf of the BRDF strategy: (1 − k_s)·cos/π + k_s·p_vndf."""
    return ((1.0 - ks) * brdf.pdf_cosine_hemisphere(local_wi)
            + ks * brdf.pdf_ggx_vndf(local_wo, local_wi, alpha))


def shade(pts: ShadingPoints, env, visibility, cfg: ShadingConfig, seed: int = 0,
          env_theta=None):
    """Linear outgoing radiance [N] (``mi.Color3f``) of every shading point.

    Differentiable w.r.t. the materials in ``pts``, the environment map's parameter
    (``env_theta`` overrides the map's own: θ of ``OctEnvmap``, ``data`` of ``octenvmap``)
    and, for SOPs, the probe atlas. Sampled directions and pdfs are detached (the estimator
    is unbiased for every parameter value, so its derivative is the integral's).
    """
    n_pts, s = pts.count, cfg.rays
    visibility.prepare(pts)
    n_env = s // 2 if cfg.sampling == "mis" else 0      # MIS: the first S//2 from the map
    if cfg.decorrelate or cfg.sampling == "mis":
        blocks = [n_env, s - n_env] if n_env else [s]
        pid, sid, u, u_lobe = sample_points(n_pts, s, seed, cfg.decorrelate, blocks)
    else:       # the paper's shared rotated Hammersley set
        u_np = direction_set(s, seed).astype(np.float32)                   # [S, 2]
        idx = dr.arange(mi.UInt32, n_pts * s)
        pid, sid = idx // s, idx % s                                       # [N*S]
        u = dr.gather(mi.Point2f, to_jit(mi.Point2f, u_np.T), sid)
        u_lobe = None
    # Per-point values are read by S consecutive lanes: ReduceMode.Local pre-reduces equal
    # neighbouring indices in the backward scatter-add. (Expand would size its per-thread
    # copies by the point count, which changes per view, and recompile every iteration.)
    L_ = dr.ReduceMode.Local
    a = dr.gather(mi.Color3f, pts.albedo, pid, mode=L_)
    r = dr.gather(mi.Float, pts.roughness, pid, mode=L_)
    m = dr.gather(mi.Float, pts.metallic, pid, mode=L_)
    if cfg.min_roughness > 0:     # closed: a roughness at the floor keeps its gradient
        r = dr.select(r < cfg.min_roughness, cfg.min_roughness, r)     # NaN stays NaN
    n = dr.gather(mi.Vector3f, dr.detach(pts.normal), pid)
    wo = dr.gather(mi.Vector3f, dr.detach(pts.wo), pid)
    with dr.suspend_grad():
        tx, ty = brdf.frame_from_normal(n)
        if cfg.sampling == "mis":
            lwo = mi.Vector3f(dr.dot(wo, tx), dr.dot(wo, ty), dr.dot(wo, n))
            alpha = brdf.ggx_alpha(dr.detach(r))
            ks = _spec_share(dr.detach(a), dr.detach(m), dr.maximum(lwo.z, 0.0))
            use_env = sid < n_env
            d_env, _ = env.sample_world(u)
            l_cos, _ = brdf.sample_cosine_hemisphere(u)
            l_ggx, _ = brdf.sample_ggx_vndf(u, lwo, alpha)
            l_brdf = dr.select(u_lobe < ks, l_ggx, l_cos)
            d_brdf = dr.normalize(tx * l_brdf.x + ty * l_brdf.y + n * l_brdf.z)
            wi = dr.select(use_env, d_env, d_brdf)
            lwi = mi.Vector3f(dr.dot(wi, tx), dr.dot(wi, ty), dr.dot(wi, n))
            # balance heuristic over the two strategies = the mixture pdf
            c_env = n_env / s
            pdf = c_env * env.pdf_world(wi) + (1.0 - c_env) * _brdf_pdf(lwo, lwi, alpha, ks)
        else:
            if cfg.sampling == "uniform":
                local, pdf = brdf.sample_uniform_hemisphere(u)
            else:
                local, pdf = brdf.sample_cosine_hemisphere(u)
            wi = dr.normalize(tx * local.x + ty * local.y + n * local.z)
    f = brdf.eval_brdf(a, r, m, n, wo, wi)
    cos_i = dr.maximum(dr.dot(wi, n), 0.0)
    L_dir = env.eval_world(wi, env_theta)
    if cfg.occlusion or cfg.indirect:
        occ, L_in = visibility.lookup(pid, wi, cfg.indirect)
    else:
        occ, L_in = mi.Float(0.0), None
    L = (1.0 - occ) * L_dir if cfg.occlusion else L_dir
    if cfg.indirect and L_in is not None:
        L = L + L_in
    ok = (pdf > 0.0) & (cos_i > 0.0)
    contrib = dr.select(ok, f * L * cos_i / dr.maximum(pdf, 1e-12), 0.0)  # [N*S]
    dr.eval(contrib)          # evaluate the wide RGB before the block sum (faster)
    return dr.block_sum(contrib, s) / s                                    # [N]
