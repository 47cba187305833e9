"""Clipped regions of an EV-0 panorama and the light head's features for them.

Split from ``lighting.lights`` (which re-exports every name here): a region is a connected
set of observed pixels clipped at EV 0 (``clipped_regions``), described by ``FEATURES``
(``region_features``: 27 scale-free descriptors of the region and its surroundings, then 3
of context against the panorama's other regions, ``_context``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comgs_dr.core.colorspace import LUMA, srgb_decode
from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles
from comgs_dr.lighting.hdr import SAT, check_ldr_mask, label_equirect

__all__ = ["Region", "clipped_regions", "FEATURES", "N_BASE_FEATURES", "region_features",
           "ring_colour", "MAX_REGIONS", "BANDS_DEG", "SAT"]

MAX_REGIONS = 8            # regions per panorama given to the head (largest observed power)
BANDS_DEG = ((0.0, 3.0), (3.0, 10.0), (10.0, 30.0))   # rings beyond the region's radius


@dataclass
class Region:
    pixels: np.ndarray        # [H, W] bool
    direction: np.ndarray     # [3] unit, luminance·dω-weighted centroid
    solid_angle: float        # sr
    seen_power: np.ndarray    # [3] Σ unexpose(ldr) dω over the region (EV-0 radiance units)


def _unit(v):
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.array([0.0, 0.0, 1.0])


def _check(ldr, mask):
    return check_ldr_mask(ldr, mask, "lights")


def clipped_regions(ldr, mask, sat: float = SAT, max_regions: int = MAX_REGIONS,
                    white_core: bool = True) -> list:
    """Connected regions of observed pixels with max channel ≥ ``sat`` in the EV-0 LDR
    panorama ``ldr`` [H, W, 3] (mask [H, W], 1 = observed), largest seen power first.

    ``white_core``: keep only regions with at least one pixel clipped in every channel. A
    light's core saturates white; a region clipped in one channel only is a saturated
    colour (a deep sky), or, in a reconstructed scene, a single sky texel at blue = 1; such
    specks beside the sun make the head read the scene as many lights and give the sun far
    too little power."""
    ldr, seen = _check(ldr, mask)
    h, w = seen.shape
    clipped = seen & (ldr.max(-1) >= sat)
    lab, n = label_equirect(clipped)
    if n and white_core:
        white = np.bincount(lab.ravel(), (clipped & (ldr.min(-1) >= sat)).ravel(), n + 1) > 0
        keep = np.flatnonzero(white[1:]) + 1                        # labels with a white core
        remap = np.zeros(n + 1, np.int64)
        remap[keep] = np.arange(1, len(keep) + 1)
        lab, n = remap[lab], len(keep)
    if n == 0:
        return []
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    lin = srgb_decode(ldr)                                                    # [H, W, 3]
    lum = lin @ LUMA
    d = equirect_directions(h, w)
    flat = lab.ravel()
    area = np.bincount(flat, dw.ravel(), n + 1)
    power = np.stack([np.bincount(flat, (lin[..., c] * dw).ravel(), n + 1) for c in range(3)], -1)
    wl = (lum * dw).ravel()
    dsum = np.stack([np.bincount(flat, d[..., c].ravel() * wl, n + 1) for c in range(3)], -1)
    order = np.argsort(-(power @ LUMA)[1:], kind="stable")[:max_regions] + 1
    return [Region(lab == i, _unit(dsum[i]), float(area[i]), power[i].copy()) for i in order]


FEATURES = (["log_solid_angle", "log_pixel_solid_angle", "elevation", "abs_elevation",
             "outdoor", "indoor", "unknown", "log_regions", "clipped_fraction",
             "fully_clipped", "compactness"]
            + [f"ring{i}_{k}" for i in range(len(BANDS_DEG))
               for k in ("seen", "clipped", "log_lum", "blue")]
            + ["log_mean_lum", "log_upper_lum", "log_lower_lum", "coverage"]
            # context: the region against the panorama's other regions (``_context``)
            + ["log_seen_vs_max", "seen_rank", "log_seen_share"])
N_BASE_FEATURES = 27       # heads fitted before the context features use this prefix


def _mean_lum(lum, sel, dw) -> float:
    wgt = (sel * dw).sum()
    return float((lum * sel * dw).sum() / wgt) if wgt > 0 else 0.0


def region_features(ldr, mask, regions, label: int = 2, sat: float = SAT) -> np.ndarray:
    """[R, len(FEATURES)] float32 descriptors of ``regions`` (``clipped_regions``) in the EV-0
    panorama; luminances are EV-0 radiance (white level 1), logs of (x + 1e-3).

    "compactness" (solid angle / the cap reaching the farthest pixel centre, that angle
    floored at 1e-3°) is resolution-dependent and huge for a region of one to three pixels,
    whose centres barely leave the centroid: up to 2.5e6 (8 % of the training regions above
    100; the head standardises it by a std of 4.3e5, so it is near constant for the rest).
    It stays because the shipped head was fitted with it; what it contributes is below the
    spread between fitting seeds."""
    ldr, seen = _check(ldr, mask)
    h, w = seen.shape
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    d = equirect_directions(h, w)
    lin = srgb_decode(ldr)
    lum = lin @ LUMA
    clipped = seen & (ldr.max(-1) >= sat)
    unclipped = seen & ~clipped
    seen_area = float((seen * dw).sum())
    up = d[..., 2] > 0
    glob = [np.log(_mean_lum(lum, unclipped, dw) + 1e-3),
            np.log(_mean_lum(lum, unclipped & up, dw) + 1e-3),
            np.log(_mean_lum(lum, unclipped & ~up, dw) + 1e-3), seen_area / (4 * np.pi)]
    onehot = np.eye(3)[int(label)]
    rows = []
    for r in regions:
        cosang = np.clip(d @ r.direction, -1.0, 1.0)
        ang = np.degrees(np.arccos(cosang))                                  # [H, W]
        radius = np.degrees(np.sqrt(r.solid_angle / np.pi))
        rmax = float(ang[r.pixels].max())
        f = [np.log(r.solid_angle), np.log(4 * np.pi / (h * w)),
             r.direction[2], abs(r.direction[2]), *onehot, np.log1p(len(regions)),
             float((clipped * dw).sum()) / max(seen_area, 1e-12),
             float((r.pixels & (ldr.min(-1) >= sat)).sum()) / max(int(r.pixels.sum()), 1),
             r.solid_angle / (2 * np.pi * (1 - np.cos(np.radians(min(max(rmax, 1e-3), 180.0)))))]
        for lo, hi in BANDS_DEG:
            band = (ang >= radius + lo) & (ang < radius + hi) & ~r.pixels
            ba = float((band * dw).sum())
            bs = band & seen
            bu = band & unclipped
            rgb = (lin * (bu * dw)[..., None]).sum((0, 1))
            f += [float((bs * dw).sum()) / max(ba, 1e-12),
                  float((band & clipped).sum()) / max(int(bs.sum()), 1),
                  np.log(_mean_lum(lum, bu, dw) + 1e-3),
                  float(rgb[2] / rgb.sum()) if rgb.sum() > 0 else 1.0 / 3.0]
        rows.append(f + glob)
    rows = np.asarray(rows, np.float32).reshape(len(regions), N_BASE_FEATURES)
    return np.concatenate([rows, _context(regions)], 1)


def _context(regions) -> np.ndarray:
    """[R, 3] float32: each region's log seen luminance power minus the largest one's, its
    rank by seen power (0 = largest) and log of its share of the regions' seen power. The
    other features describe a region alone; these let the head rank look-alike lamps
    against each other (with the listwise loss of ``train-light-head --rank-weight``)."""
    ls = np.log(np.maximum([float(r.seen_power @ LUMA) for r in regions], 1e-12))
    if not len(ls):
        return np.zeros((0, 3), np.float32)
    rank = np.argsort(np.argsort(-ls, kind="stable"), kind="stable")
    share = ls - (ls.max() + np.log(np.exp(ls - ls.max()).sum()))
    return np.stack([ls - ls.max(), rank, share], 1).astype(np.float32)


def ring_colour(ldr, mask, region: Region, sat: float = SAT, max_deg: float = 10.0):
    """[3] chromaticity (luminance 1) of the unclipped observed pixels within ``max_deg`` of
    the region (the glow around a sun, the wall around a lamp); white if none is seen."""
    ldr, seen = _check(ldr, mask)
    h, w = seen.shape
    d = equirect_directions(h, w)
    ang = np.degrees(np.arccos(np.clip(d @ region.direction, -1.0, 1.0)))
    radius = np.degrees(np.sqrt(region.solid_angle / np.pi))
    sel = seen & (ldr.max(-1) < sat) & (ang < radius + max_deg) & ~region.pixels
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    rgb = (srgb_decode(ldr) * (sel * dw)[..., None]).sum((0, 1))
    lum = float(rgb @ LUMA)
    return rgb / lum if lum > 0 else np.ones(3)
