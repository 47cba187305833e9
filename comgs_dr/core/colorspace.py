"""Colour: the sRGB transfer pair in Dr.Jit and in NumPy/torch, Rec. 709 luminance, and a
tone map for HDR previews.

NumPy arrays go through colour-science (IEC 61966-2-1 ``colour.cctf_encoding`` /
``cctf_decoding``, the sRGB colourspace's luminance); it is imported on first use (its
import takes ~1 s, which ``comgs --help`` should not pay). The Dr.Jit and torch versions
are hand-written because they must stay differentiable inside JIT-traced / autograd
graphs, which colour-science (NumPy only) cannot be; tests/test_colour.py checks them
against colour-science's values.

A surfel radiance field fitted to sRGB photos stores display-encoded colour (3DGS
convention); stages that need linear radiance convert *after* compositing
(:func:`unpremultiplied_to_linear`). Callers clip where their data needs it.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def srgb_to_linear(c):
    """Display sRGB -> linear; values above 1 follow the power curve (HDR-safe), < 0 -> 0.
    Hand-written: Dr.Jit (differentiable, JIT-traced). y^2.4 = y²·y^0.4 keeps float32
    within 1e-6 of colour-science up to 1e6 (a single power was 4e-6 off)."""
    c = dr.maximum(c, 0.0)
    y = (c + 0.055) / 1.055
    return dr.select(c <= 0.04045, c / 12.92, dr.square(y) * dr.power(y, 0.4))


def linear_to_srgb(c):
    """Linear -> display sRGB (no clamp above 1; negative values -> 0).
    Hand-written: Dr.Jit (differentiable, JIT-traced); x^(1/2.4) = √x·x^(-1/12) for float32
    accuracy (as :func:`srgb_to_linear`)."""
    c = dr.maximum(c, 0.0)
    x = dr.maximum(c, 1e-12)
    return dr.select(c <= 0.0031308, c * 12.92,
                     1.055 * dr.sqrt(x) * dr.power(x, -1.0 / 12.0) - 0.055)


def unpremultiplied_to_linear(color, weight, eps: float = 1e-4):
    """Linear radiance of a composited (premultiplied) sRGB colour with coverage ``weight``:
    W · srgb_to_linear(C / W); 0 where W < eps."""
    w = dr.maximum(weight, eps)
    return dr.select(weight >= eps, weight * srgb_to_linear(color / w), 0.0)


# Rec. 709 / sRGB luminance weights: the Y row of colour-science's sRGB RGB->XYZ matrix
# (pinned by tests/test_colour.py), a constant so Dr.Jit/torch code and import need no colour.
LUMA = np.array([0.2126, 0.7152, 0.0722])


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


def _colour():
    import colour  # lazy: ~1 s to import, only needed when NumPy colour maths runs
    return colour


def _np_cctf(fn, x: np.ndarray) -> np.ndarray:
    """colour-science transfer ``fn`` ('sRGB') of ``x``, in ``x``'s float dtype."""
    return np.asarray(fn(x, function="sRGB"), dtype=x.dtype)


def srgb_encode(x):
    """Linear -> sRGB (no clamp above 1; the linear segment extends to negatives).
    NumPy: ``colour.cctf_encoding``; torch: hand-written (autograd)."""
    x = as_float(x)
    if not is_torch(x):
        return _np_cctf(_colour().cctf_encoding, x)
    xc = x.clip(0.0031308, None)                                   # clip: finite grads
    hi = 1.055 * xc.sqrt() * xc ** (-1.0 / 12.0) - 0.055           # x^(1/2.4), float32-accurate
    return _where(x <= 0.0031308, 12.92 * x, hi)


def srgb_decode(c):
    """sRGB -> linear (inverse of ``srgb_encode``). NumPy: ``colour.cctf_decoding``;
    torch: hand-written (autograd)."""
    c = as_float(c)
    if not is_torch(c):
        return _np_cctf(_colour().cctf_decoding, c)
    y = (c.clip(0.04045, None) + 0.055) / 1.055
    return _where(c <= 0.04045, c / 12.92, y * y * y ** 0.4)      # y^2.4, float32-accurate


def luminance(rgb) -> np.ndarray:
    """Relative luminance Y [...] of linear sRGB [..., 3] (colour-science's sRGB RGB->XYZ)."""
    colour = _colour()
    return colour.RGB_to_XYZ(as_float(rgb), colour.RGB_COLOURSPACES["sRGB"])[..., 1]


def tonemap(hdr, exposure: float = 1.0) -> np.ndarray:
    """Display sRGB [..., 3] in [0, 1] of linear HDR [..., 3] for previews: the global
    Reinhard et al. (2002) operator L_d = L / (1 + L) on luminance, colours scaled by L_d / L
    (hue kept), then sRGB-encoded and clipped. colour-science has no tone-mapping operator,
    so this is written here on its luminance and transfer functions."""
    hdr = np.maximum(as_float(hdr), 0.0) * float(exposure)
    lum = luminance(hdr)[..., None]
    scale = np.where(lum > 0, 1.0 / (1.0 + lum), 1.0)          # L_d / L
    return np.clip(srgb_encode(hdr * scale), 0.0, 1.0)


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
