"""Where step 2's learnt capture light starts: the light's low-frequency shape read off the
object's own shading.

Why: step 2 learns the capture's light and the surfels' albedo together, and each surfel's
albedo is its own Adam variable that explains its pixels within a few steps, while the
shared map only gets what is left. From the paper's constant start the map stays too flat
and the albedo takes the shading: on the demo's torus the learnt studio's irradiance facing
its key light against facing away was 5.4 (the true map's: 10.2), and the surfels facing
away came out with 0.64 of the albedo of those facing the key, for an object of one colour
(docs/composite.md, "The learnt light's start"). Relit under another light that shading
stays as dark and light patches.

What: on a Lambertian surface of albedo ρ the linear radiance is ρ/π · E(n), and the
irradiance E is smooth: its spherical harmonics up to degree 2 hold almost all of it
(Ramamoorthi and Hanrahan 2001, "An efficient representation for irradiance environment
maps"). A least-squares fit of the covered pixels' linear luminance to the nine SH of their
normals gives E's coefficients E_lm up to ρ; the radiance coefficients are E_lm / Â_l with
Â_0 = π, Â_1 = 2π/3, Â_2 = π/4 (the clamped-cosine kernel). The map is that radiance at
the texel directions, grey (the white-light prior: the colour split stays the albedo's),
at the level of an albedo ``albedo`` (step 2's start), with a floor: a degree-2 fit of a
compact light rings below zero opposite it. Texture, occlusion and highlights are noise to
the fit; the optimisation refines the map from there. Hand-written (a 9-column least
squares): no library fits irradiance SH to surface samples.
"""
from __future__ import annotations

from math import pi

import numpy as np

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.octahedral import texel_directions_np, texel_solid_angles_np
from comgs_dr.lighting.hdr import real_sh_basis

__all__ = ["light_from_shading", "KERNEL", "MIN_SAMPLES", "FLOOR"]

KERNEL = np.array([pi] + [2 * pi / 3] * 3 + [pi / 4] * 5)   # Â_l per coefficient (l = 0, 1, 2)
MIN_SAMPLES = 200          # covered pixels below which the fit is not trusted
FLOOR = 0.05               # radiance floor, × the map's mean
RIDGE = 1e-6               # relative Tikhonov weight (normals covering half the sphere)


def light_from_shading(normals, linear_rgb, res: int, albedo: float = 0.5,
                       floor: float = FLOOR) -> tuple[np.ndarray, dict]:
    """([res, res, 3] octahedral radiance, info): the grey degree-2 light whose Lambertian
    shading of albedo ``albedo`` best fits (least squares) the linear luminance of
    ``linear_rgb`` [P, 3] at unit ``normals`` [P, 3] (facing the camera), floored at
    ``floor`` × its mean radiance. info: ``samples``, ``fit_r2`` (share of the luminance's
    variance the shading explains), ``contrast`` (the floored map's max / min irradiance
    over the 26 axis-and-diagonal normals). ValueError: fewer than ``MIN_SAMPLES`` samples, non-finite
    inputs, or a fit with no light (mean radiance ≤ 0)."""
    n = np.asarray(normals, np.float64)
    c = np.asarray(linear_rgb, np.float64)
    if n.ndim != 2 or n.shape[1] != 3 or c.shape != n.shape:
        raise ValueError(f"light_from_shading: normals and colours must both be [P, 3], got "
                         f"{n.shape} and {c.shape}")
    if len(n) < MIN_SAMPLES:
        raise ValueError(f"light_from_shading: {len(n)} samples, need ≥ {MIN_SAMPLES}")
    if not (np.isfinite(n).all() and np.isfinite(c).all()):
        raise ValueError("light_from_shading: non-finite normals or colours")
    if not (albedo > 0 and 0 < floor < 1):
        raise ValueError(f"light_from_shading: albedo must be > 0 and floor in (0, 1), got "
                         f"{albedo}, {floor}")
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    y = c @ LUMA
    B = real_sh_basis(n, 2)                                         # [P, 9]
    A = B.T @ B
    e = np.linalg.solve(A + RIDGE * np.trace(A) / 9 * np.eye(9), B.T @ y)   # ρ/π · E_lm
    r2 = 1.0 - float(np.var(y - B @ e) / max(np.var(y), 1e-300))
    L_lm = e * pi / albedo / KERNEL                                 # radiance coefficients
    dirs = texel_directions_np(res)
    rad = real_sh_basis(dirs, 2) @ L_lm
    mean = float(rad.mean())
    if not mean > 0:
        raise ValueError("light_from_shading: the fitted light has no power (mean ≤ 0)")
    rad = np.maximum(rad, floor * mean)
    probe = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                      if (i, j, k) != (0, 0, 0)], np.float64)
    probe /= np.linalg.norm(probe, axis=1, keepdims=True)
    E = np.maximum(probe @ dirs.T, 0.0) @ (rad * texel_solid_angles_np(res))   # the map's
    info = {"samples": int(len(n)), "fit_r2": r2, "contrast": float(E.max() / E.min())}
    return np.repeat(rad.reshape(res, res, 1), 3, axis=2), info
