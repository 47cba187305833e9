"""Spherical Gaussians: L(ω) = a·exp(λ(ω·μ − 1)), the lobes of ``lighting.lights``.

``sg_integral`` is ∫ = 2π/λ·(1 − e^{−2λ}); ``sg_sharpness`` inverts it for a solid angle;
``render_lobes`` draws lobes into an equirect map with their exact power Σ L dω (normalised on
the pixel grid, so a lobe narrower than a pixel keeps its power). NumPy, hand-written: three
closed forms on host arrays (the lobes of one panorama), with nothing in Mitsuba to reuse.
"""
from __future__ import annotations

import numpy as np

from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles

__all__ = ["sg_integral", "sg_sharpness", "render_lobes"]


def sg_integral(sharpness) -> np.ndarray:
    """∫ exp(λ(ω·μ − 1)) dω = 2π/λ·(1 − e^{−2λ}) (→ 4π as λ → 0)."""
    lam = np.maximum(np.asarray(sharpness, np.float64), 1e-12)
    return 2.0 * np.pi * -np.expm1(-2.0 * lam) / lam


def sg_sharpness(solid_angle) -> np.ndarray:
    """λ whose unit-amplitude SG integrates to ``solid_angle`` (0 < Ω < 4π), by bisection in
    log λ (the integral is monotone in λ)."""
    om = np.asarray(solid_angle, np.float64)
    if not np.all((om > 0) & (om < 4 * np.pi)):
        raise ValueError(f"sg_sharpness: solid angles must lie in (0, 4π), got {om}")
    lo, hi = np.full(om.shape, -12.0), np.full(om.shape, 30.0)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        big = sg_integral(np.exp(mid)) > om          # too wide: sharpen
        lo, hi = np.where(big, mid, lo), np.where(big, hi, mid)
    return np.exp(0.5 * (lo + hi))


def render_lobes(lobes, h: int, w: int) -> np.ndarray:
    """[h, w, 3] equirect radiance of lobes (dicts with ``direction`` [3], ``sharpness``,
    ``rgb_power`` [3]); each lobe is normalised on the pixel grid to Σ L dω = rgb_power."""
    out = np.zeros((h, w, 3))
    if not lobes:
        return out
    d = equirect_directions(h, w)                                             # [h, w, 3]
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))                    # [h, w]
    for lb in lobes:
        mu = np.asarray(lb["direction"], np.float64)
        mu = mu / np.linalg.norm(mu)
        g = np.exp(float(lb["sharpness"]) * (d @ mu - 1.0))                   # [h, w]
        if (g * dw).sum() <= 0:                     # narrower than the grid: nearest pixel
            g = (d @ mu >= (d @ mu).max()).astype(np.float64)
        out += (g / (g * dw).sum())[..., None] * np.asarray(lb["rgb_power"], np.float64)
    return out
