"""Colour: the sRGB transfer pair in Dr.Jit and in NumPy/torch, and Rec. 709 luminance.

A surfel radiance field fitted to sRGB photos stores display-encoded colour (3DGS
convention); stages that need linear radiance convert *after* compositing
(:func:`unpremultiplied_to_linear`). Callers clip where their data needs it.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


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


LUMA = np.array([0.2126, 0.7152, 0.0722])      # Rec. 709 / sRGB luminance weights


def is_torch(x) -> bool:
    """A torch tensor? (torch is optional and imported only when a tensor comes in.)"""
    if type(x).__module__.split(".")[0] != "torch":
        return False
    import torch  # optional: only reached when a torch tensor comes in
    return isinstance(x, torch.Tensor)


def as_float(x):
    """Tensor -> as is; anything else -> floating NumPy array (float32 kept)."""
    if is_torch(x):
        return x
    a = np.asarray(x)
    return a if np.issubdtype(a.dtype, np.floating) else a.astype(np.float64)


def _where(c, a, b):
    if is_torch(a):
        import torch  # optional: only reached for torch tensors
        return torch.where(c, a, b)
    return np.where(c, a, b)


def srgb_encode(x):
    """Linear -> sRGB (no clamp above 1; the linear segment extends to negatives)."""
    x = as_float(x)
    hi = 1.055 * x.clip(0.0031308, None) ** (1.0 / 2.4) - 0.055   # clip: finite grads
    return _where(x <= 0.0031308, 12.92 * x, hi)


def srgb_decode(c):
    """sRGB -> linear (inverse of ``srgb_encode``)."""
    c = as_float(c)
    hi = ((c.clip(0.04045, None) + 0.055) / 1.055) ** 2.4
    return _where(c <= 0.04045, c / 12.92, hi)


def display_composite(img, background: float):
    """Linear RGBA [H, W, 4] (premultiplied, alpha = coverage W) -> display sRGB [H, W, 3]
    over ``background``: W·srgb(C/W) + (1 − W)·bg, as the photos (differentiable)."""
    h, w = img.shape[0], img.shape[1]
    flat = img.array
    base = dr.arange(mi.UInt32, h * w) * 4
    a = dr.gather(mi.Float, flat, base + 3)
    rgb = mi.Color3f(*(dr.gather(mi.Float, flat, base + c) for c in range(3)))
    straight = rgb / dr.maximum(a, 1e-6)
    out = a * linear_to_srgb(straight) + (1.0 - a) * background
    return mi.TensorXf(dr.ravel(out), shape=(h, w, 3))
