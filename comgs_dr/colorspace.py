"""sRGB transfer functions in Dr.Jit (NumPy twins live in ``surfels.from_mesh``).

A surfel radiance field fitted to sRGB photos stores display-encoded colour (DESIGN.md §4);
stages that need linear radiance convert *after* compositing.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


def srgb_to_linear(c):
    """Display sRGB -> linear; values above 1 follow the power curve (HDR-safe), < 0 -> 0."""
    c = dr.maximum(c, 0.0)
    return dr.select(c <= 0.04045, c / 12.92, dr.power((c + 0.055) / 1.055, 2.4))


def linear_to_srgb(c):
    """Linear -> display sRGB (no clamp above 1; negative values -> 0)."""
    c = dr.maximum(c, 0.0)
    return dr.select(c <= 0.0031308, c * 12.92,
                     1.055 * dr.power(dr.maximum(c, 1e-12), 1.0 / 2.4) - 0.055)


def unpremultiplied_to_linear(color, weight, eps: float = 1e-4):
    """Linear radiance of a composited (premultiplied) sRGB colour with coverage ``weight``:
    W · srgb_to_linear(C / W); 0 where W < eps."""
    w = dr.maximum(weight, eps)
    return dr.select(weight >= eps, weight * srgb_to_linear(color / w), 0.0)
