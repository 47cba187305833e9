"""Equirectangular maps in NumPy: directions, pixel solid angles, coverage, sampling.

Convention (Blender's Z-up equirect, used by every map file of the package):
u = 0.5 − atan2(d_y, d_x)/2π, v = acos(d_z)/π, v = 0 the top row (+Z); pixel (i, j) has its
centre at ((i + 0.5)/W, (j + 0.5)/H). +X is at the image centre, +Y at u = 0.25.
"""
from __future__ import annotations

from math import pi

import numpy as np


def solid_angle_weights(height: int) -> np.ndarray:
    """[H] relative solid angle of an equirect row (sin θ at the row centre)."""
    return np.sin((np.arange(height) + 0.5) / height * np.pi)


def coverage(alpha) -> float:
    """Solid-angle-weighted fraction of covered directions of an [H, W] equirect ``alpha``
    (1 for a fully covered panorama, 0.5 for exactly one covered hemisphere)."""
    a = np.asarray(alpha, np.float64)
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"coverage: expected an [H, W] alpha image, got shape {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"coverage: alpha has {int((~np.isfinite(a)).sum())} non-finite values")
    w = solid_angle_weights(a.shape[0])
    return float((a * w[:, None]).sum() / (w.sum() * a.shape[1]))


def pixel_directions(width: int, height: int, start: int, stop: int, supersample: int = 1,
                     rng=None, equal_area: bool = False) -> np.ndarray:
    """Unit directions [(stop − start)·s², 3] of pixels start..stop−1 (row-major), the s²
    sub-rays of a pixel contiguous. s = 1: pixel centres; s > 1: one jittered ray per
    stratum (``rng`` a numpy Generator), uniform in (u, v), or with ``equal_area`` uniform in
    (u, cos θ): each stratum then covers an equal solid angle of the pixel, so the strata's
    mean is the pixel's solid-angle average (a small sun near a pole is not over-weighted)."""
    s = int(supersample)
    p = np.arange(start, stop)
    i, j = (p % width).astype(np.float64), (p // width).astype(np.float64)
    if s == 1:
        u, v = (i + 0.5) / width, (j + 0.5) / height
    else:
        sy, sx = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
        sx, sy = sx.ravel()[None, :], sy.ravel()[None, :]                   # [1, s²]
        jit = (rng or np.random.default_rng(0)).uniform(0.0, 1.0, (2, len(p), s * s))
        u = ((i[:, None] + (sx + jit[0]) / s) / width).ravel()
        t = (sy + jit[1]) / s                                               # [P, s²] in the pixel
        if equal_area:
            z0, z1 = np.cos(np.pi * j / height)[:, None], np.cos(np.pi * (j + 1) / height)[:, None]
            v = (np.arccos(np.clip(z0 - t * (z0 - z1), -1.0, 1.0)) / np.pi).ravel()
        else:
            v = ((j[:, None] + t) / height).ravel()
    return equirect_uv_to_dir_np(np.stack([u, v], -1))


def equirect_dir_to_uv_np(d):
    """[N, 3] unit directions -> [N, 2] equirect uv (Blender Z-up convention)."""
    d = np.asarray(d, np.float64)
    u = (0.5 - np.arctan2(d[:, 1], d[:, 0]) / (2 * np.pi)) % 1.0
    v = np.arccos(np.clip(d[:, 2], -1.0, 1.0)) / np.pi
    return np.stack([u, v], -1)


def equirect_uv_to_dir_np(uv):
    uv = np.asarray(uv, np.float64)
    phi = (0.5 - uv[:, 0]) * 2 * np.pi
    theta = uv[:, 1] * np.pi
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], -1)


def sample_equirect_np(img, uv):
    """Bilinear lookup of an [H, W, C] equirect image at [N, 2] uv (wraps in u)."""
    h, w = img.shape[:2]
    x = uv[:, 0] * w - 0.5
    y = np.clip(uv[:, 1] * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x1, y1 = (x0 + 1) % w, np.minimum(y0 + 1, h - 1)
    x0 %= w
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x1]
            + (1 - fx) * fy * img[y1, x0] + fx * fy * img[y1, x1])


def pixel_solid_angles(h: int, w: int) -> np.ndarray:
    """[H, 1] exact solid angle of each equirect pixel row (sums to 4π over the image)."""
    edges = np.cos(np.linspace(0.0, pi, h + 1))
    return ((edges[:-1] - edges[1:]) * (2.0 * pi / w))[:, None]


def equirect_directions(h: int, w: int) -> np.ndarray:
    """[H, W, 3] unit directions of the pixel centres (Blender Z-up equirect)."""
    u, v = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    return equirect_uv_to_dir_np(np.stack([u.ravel(), v.ravel()], -1)).reshape(h, w, 3)


def solid_angle_image(h: int, w: int) -> np.ndarray:
    """[h, w] solid angle of every equirect pixel (sums to 4π)."""
    return np.broadcast_to(pixel_solid_angles(h, w), (h, w))


def resize_mask(mask, h: int, w: int) -> np.ndarray:
    """Nearest-neighbour resize of a [h', w'] bool mask (a traced panorama's observed
    pixels) to the [h, w] of a map built at another resolution."""
    mask = np.asarray(mask, bool)
    if mask.shape != (h, w):
        oh, ow = mask.shape
        mask = mask[(np.arange(h) * oh) // h][:, (np.arange(w) * ow) // w]
    return mask
