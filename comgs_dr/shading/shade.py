"""Deferred physically based shading of G-buffer points (paper eqs. render_equation,
illumination, knn).

For each shading point x (normal n, view direction ω_o, albedo a, roughness r, metallic m)
and S_r directions ω_i drawn from a randomly rotated Hammersley set:

    C_pbr(x) = 1/S_r · Σ_i f(ω_o, ω_i) · L_i(ω_i) · (ω_i·n) / pdf(ω_i),
    L_i(ω) = (1 − O(ω)) · L_dir(ω) + L_in(ω),

with pdf = 1/2π (uniform hemisphere, the paper's 2π/S_r estimator) or cos/π (cosine).
L_dir is the octahedral environment map; O and L_in come from a *visibility source*:

* :class:`SopVisibility` — KNN interpolation of the Surface Octahedral Probes' textures
  (computed once per set of points, eq. knn), differentiable w.r.t. the probe atlas;
* :class:`TraceVisibility` — per-call ray tracing through the surfels (IRGS-style
  baseline), detached and evaluated before shading;
* :class:`NoVisibility` — O = 0, L_in = 0 (convex objects, or to isolate direct light).

All (point, direction) pairs form one wide array (never a Python loop over
directions: one kernel per shading call), and each source can skip the indirect term (``indirect=False``).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.shading import brdf


@dataclass(frozen=True)
class ShadingConfig:
    rays: int = 128                  # S_r (sec. 4.1: 128 in training, 256 for rendering)
    sampling: str = "uniform"        # 'uniform' (paper) | 'cosine'
    indirect: bool = True            # add L_in (inter-reflections)
    occlusion: bool = True           # apply (1 − O) to the environment light

    def __post_init__(self):
        if self.rays < 1:
            raise ValueError(f"ShadingConfig: rays must be ≥ 1, got {self.rays}")
        if self.sampling not in ("uniform", "cosine"):
            raise ValueError(f"ShadingConfig: sampling must be 'uniform' or 'cosine', "
                             f"got {self.sampling!r}")


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


def shade(pts: ShadingPoints, env, visibility, cfg: ShadingConfig, seed: int = 0,
          env_theta=None):
    """Linear outgoing radiance [N] (``mi.Color3f``) of every shading point.

    Differentiable w.r.t. the materials in ``pts``, the environment map's θ (``env_theta``
    overrides ``env.theta``) and, for SOPs, the probe atlas.
    """
    n_pts, s = pts.count, cfg.rays
    visibility.prepare(pts)
    u = direction_set(s, seed).astype(np.float32)                          # [S, 2]
    idx = dr.arange(mi.UInt32, n_pts * s)
    pid, sid = idx // s, idx % s                                           # [N*S]
    uu = dr.gather(mi.Point2f, mi.Point2f(u[:, 0], u[:, 1]), sid)
    if cfg.sampling == "uniform":
        local, pdf = brdf.sample_uniform_hemisphere(uu)
    else:
        local, pdf = brdf.sample_cosine_hemisphere(uu)
    n = dr.gather(mi.Vector3f, dr.detach(pts.normal), pid)
    tx, ty = brdf.frame_from_normal(n)
    wi = dr.normalize(tx * local.x + ty * local.y + n * local.z)
    wo = dr.gather(mi.Vector3f, dr.detach(pts.wo), pid)
    # Per-point values are read by S consecutive lanes: ReduceMode.Local pre-reduces equal
    # neighbouring indices in the backward scatter-add. (Expand would size its per-thread
    # copies by the point count, which changes per view, and recompile every iteration.)
    L_ = dr.ReduceMode.Local
    a = dr.gather(mi.Color3f, pts.albedo, pid, mode=L_)
    r = dr.gather(mi.Float, pts.roughness, pid, mode=L_)
    m = dr.gather(mi.Float, pts.metallic, pid, mode=L_)
    f = brdf.eval_brdf(a, r, m, n, wo, wi)
    cos_i = dr.maximum(dr.dot(wi, n), 0.0)
    L_dir = env.eval(wi, env_theta)
    if cfg.occlusion or cfg.indirect:
        occ, L_in = visibility.lookup(pid, wi, cfg.indirect)
    else:
        occ, L_in = mi.Float(0.0), None
    L = (1.0 - occ) * L_dir if cfg.occlusion else L_dir
    if cfg.indirect and L_in is not None:
        L = L + L_in
    contrib = f * L * cos_i / dr.maximum(pdf, 1e-12)                     # [N*S]
    dr.eval(contrib)          # evaluate the wide RGB before the block sum (measured faster)
    return dr.block_sum(contrib, s) / s                                    # [N]
