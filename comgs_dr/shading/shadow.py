"""Shadow ratio of scene points under placed objects (paper, "Rendering": S = L_o'/L_o).

The reconstructed scene carries baked radiance, so a new object's shadow is applied as a
ratio: for a scene point x with normal n, with the environment light L_i estimated at the
placement and O'(ω) the occlusion by the inserted objects,

    L_o  = ∫ L_i(ω) (ω·n)⁺ dω,      L_o' = ∫ (1 − O'(ω)) L_i(ω) (ω·n)⁺ dω,   S = L_o' / L_o,

per colour channel (a sun blocked under a blue sky leaves a bluish shadow). Both integrals
use the *same* S_r directions, so S ∈ [0, 1] exactly and its noise is that of the blocked
part only. Directions: half drawn from the environment map (∝ luminance × solid angle),
half cosine-weighted (the half-space below the surface is never wasted), each weighted by
the mixture pdf (balance heuristic), rotated per point (``shade.sample_points``).
O' comes from any visibility source (SOPs interpolating the cached occlusion, or tracing).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from comgs_dr.shading import brdf
from comgs_dr.shading.shade import ShadingPoints, sample_points


def shadow_ratio(x, n, env, visibility, rays: int = 256, seed: int = 0, sun=None,
                 sun_visibility=None, sun_rays: int = 16):
    """S [P] (``mi.Color3f`` in [0, 1]) at points ``x`` [P] with unit normals ``n`` [P].

    ``env``: anything with ``eval_world`` / ``sample_world`` / ``pdf_world`` (the
    ``octenvmap`` emitter, ``OctEnvmap``); ``visibility``: a source from
    :mod:`comgs_dr.shading.visibility` (only its occlusion is read). Points receiving no
    light at all (L_o = 0) get S = 1. No AD (the ratio multiplies a fixed scene colour).

    ``sun``: a :class:`comgs_dr.shading.sun.SunSplit` of ``env``: then ``rays`` integrate
    its ``rest`` with ``visibility`` and ``sun_rays`` more, drawn from the source alone,
    integrate ``sun`` with ``sun_visibility`` (traced: the probes' texels are wider than a
    sun); S = (lit_rest + lit_sun) / (full_rest + full_sun), each part its own estimate.
    """
    if rays < 2:
        raise ValueError(f"shadow_ratio: rays must be ≥ 2 (half per strategy), got {rays}")
    if sun is not None and (sun_visibility is None or sun_rays < 1):
        raise ValueError("shadow_ratio: a sun split needs sun_visibility and sun_rays ≥ 1")
    P = dr.width(x)
    with dr.suspend_grad():
        pts = ShadingPoints(position=mi.Point3f(x), normal=mi.Vector3f(n), wo=mi.Vector3f(n),
                            albedo=mi.Color3f(1.0), roughness=mi.Float(1.0),
                            metallic=mi.Float(0.0))
        visibility.prepare(pts)
        full, lit = _integrals(pts, P, env if sun is None else sun.rest, visibility, rays, seed,
                               rays // 2)
        if sun is not None:
            if sun_visibility is not visibility:
                sun_visibility.prepare(pts)
            fs, ls = _integrals(pts, P, sun.sun, sun_visibility, sun_rays, seed + 1, sun_rays)
            full, lit = full + fs, lit + ls
        S = dr.select(full > 1e-12, lit / dr.maximum(full, 1e-12), 1.0)
        S = dr.clip(S, 0.0, 1.0)
        dr.eval(S)
    return S


def _integrals(pts, P, env, visibility, rays, seed, n_env):
    """(L_o, L_o') [P] per point: mean over ``rays`` directions, ``n_env`` of them drawn
    from ``env`` and the rest cosine-weighted (balance heuristic over the mixture)."""
    blocks = [b for b in (n_env, rays - n_env) if b > 0]
    pid, sid, u, _ = sample_points(P, rays, seed, True, blocks)
    nn = dr.gather(mi.Vector3f, pts.normal, pid)
    tx, ty = brdf.frame_from_normal(nn)
    d_env, _ = env.sample_world(u)
    l_cos, _ = brdf.sample_cosine_hemisphere(u)
    d_cos = dr.normalize(tx * l_cos.x + ty * l_cos.y + nn * l_cos.z)
    wi = dr.select(sid < n_env, d_env, d_cos)
    cos = dr.dot(wi, nn)
    c_env = n_env / rays
    pdf = c_env * env.pdf_world(wi) + (1.0 - c_env) * dr.maximum(cos, 0.0) * dr.inv_pi
    ok = (cos > 0.0) & (pdf > 0.0)
    L = dr.select(ok, env.eval_world(wi) * cos / dr.maximum(pdf, 1e-12), 0.0)   # [P*S]
    occ, _ = visibility.lookup(pid, wi, False)
    full = dr.block_sum(L, rays) / rays                                         # [P]
    lit = dr.block_sum(L * (1.0 - dr.clip(occ, 0.0, 1.0)), rays) / rays
    return full, lit
