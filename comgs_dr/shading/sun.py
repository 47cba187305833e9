"""The dominant compact source of an environment map, split off so its shadow can be traced.

A cached occlusion probe stores O'(ω) in octahedral texels of 4–11° (32² / 16²), blended
across neighbouring probes: right for the sky's soft occlusion, but a sun of 0.5–3° seen
through it casts a blurred, lighter shadow than a traced one under the same map.
Splitting the map into the source's texels and the rest lets the shadow ratio trace a few
rays per pixel toward the source (exact, cheap: one compact cone) and keep the probes for
the rest. The two maps sum to the original exactly (lookups are linear in the texels), so
the split changes the estimator, not the light.

What counts as a dominant compact source: the brightest texel, grown to the texels within
``max_radius_deg`` of it that reach ``rel_threshold`` of its luminance, giving at least
``min_share`` of the irradiance of a surface facing it (a low sun holds 2 % of a sunset
map's power but most of the light on a wall facing it, and all of the shadow's edge). An overcast sky or a room lit
by a large window has none: then nothing is split and the probes carry everything.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comgs_dr.core import octahedral as octa
from comgs_dr.core.colorspace import LUMA

MIN_SHARE = 0.03          # of the irradiance facing the source
MIN_CONTRAST = 10.0       # the source's mean radiance / the map's
MAX_RADIUS_DEG = 8.0      # the source's texels lie within this cone of the brightest one
REL_THRESHOLD = 0.05      # ... and reach this fraction of its luminance


@dataclass
class SunSplit:
    """``sun``: an ``octenvmap`` holding only the source's texels; ``rest``: the others;
    ``direction`` [3]: the source's luminance-weighted world direction; ``share``: its part
    of the irradiance facing it; ``radius_deg``: the radius of a disk of its solid angle."""
    sun: object
    rest: object
    direction: np.ndarray
    share: float
    radius_deg: float


def find_sun(radiance: np.ndarray, min_share: float = MIN_SHARE,
             min_contrast: float = MIN_CONTRAST,
             max_radius_deg: float = MAX_RADIUS_DEG, rel_threshold: float = REL_THRESHOLD):
    """(mask [R, R] bool, local direction [3], share, radius in degrees) of the dominant
    compact source of an octahedral map [R, R, 3], or None when it gives < ``min_share`` of
    the irradiance facing it."""
    rad = np.asarray(radiance, np.float64)
    res = rad.shape[0]
    lum = np.maximum(rad @ LUMA, 0.0)
    dw = octa.texel_solid_angles_np(res).reshape(res, res)
    dirs = octa.texel_directions_np(res).reshape(res, res, 3)
    total = float((lum * dw).sum())
    if not np.isfinite(total) or total <= 0:
        return None
    peak = np.unravel_index(np.argmax(lum), lum.shape)
    cos = dirs @ dirs[peak]
    mask = (cos >= np.cos(np.radians(max_radius_deg))) & (lum >= rel_threshold * lum[peak])
    power = lum * dw * mask
    d = (dirs * power[..., None]).sum((0, 1))
    d /= max(np.linalg.norm(d), 1e-30)
    facing = np.maximum(dirs @ d, 0.0) * lum * dw
    share = float((facing * mask).sum() / max(facing.sum(), 1e-30))
    contrast = float(power.sum() / max((dw * mask).sum(), 1e-30)) / (total / (4 * np.pi))
    if share < min_share or contrast < min_contrast:
        return None
    radius = float(np.degrees(np.arccos(max(1.0 - (dw * mask).sum() / (2 * np.pi), -1.0))))
    return mask, d, share, radius


def split_sun(env, **kw) -> SunSplit | None:
    """Split an ``octenvmap`` emitter into its dominant compact source and the rest (same
    orientation), or None when the map has none (:func:`find_sun`'s parameters). ``env``
    must offer ``radiance_np``, ``world_transform`` and ``from_radiance`` (``octenvmap``)."""
    rad = env.radiance_np()
    found = find_sun(rad, **kw)
    if found is None:
        return None
    mask, d_local, share, radius = found
    import mitsuba as mi
    m4 = np.array(env.world_transform().matrix, np.float64).reshape(4, 4)
    to_world = mi.ScalarTransform4f(m4.tolist())
    cls = type(env)
    sun = cls.from_radiance(rad * mask[..., None], to_world, id="sun")
    rest = cls.from_radiance(rad * ~mask[..., None], to_world, id="sky")
    return SunSplit(sun, rest, m4[:3, :3] @ d_local, share, radius)
