"""A clear sky for a sun found from the scene's shadows, where the capture never looked up.

Outdoor captures rarely look at the sky. The panorama completion then guesses the unseen
upper hemisphere from what the capture saw, the ground and walls, and on the composition
benchmark its guess is the ground's warm colour: the unseen sky's power is 0.64, 0.51,
0.28 of the truth's per channel (chroma 1.22, 1.08, 0.70 against the
real map's 0.87, 0.97, 1.15), and the sun added from the shadows, k_rgb × that irradiance,
inherits the missing blue (docs/composite.md, "The unseen sky"). The shadows measure k (the
sun against the sky) but not the sky's own colour: that is the ground's albedo times the
sky, and the albedo is unknown.

When the shadows show a sun (parallel shadows across the scene: ``sun_fit``), the sky is a
daylight sky, and its colour and its distribution over the hemisphere follow from the sun's
elevation through a physical model: Mitsuba's ``sunsky`` emitter (Hosek and Wilkie's
analytic sky), used here rather than a hand-written model. Its turbidity 3 (a clear day)
gives the benchmark's real map's sky irradiance chroma within 10 % per channel at its 8°
sun (0.74, 1.02, 1.25 against 0.72, 0.93, 1.35; turbidity 8: 1.01, 1.02, 0.98). The model
supplies the shape and colour only: the unseen sky keeps the completion's luminance
irradiance on a surface facing up (the
absolute level needs the ground's albedo, which nothing measures), and observed pixels are
never changed (the panorama keeps what it saw).

Frames: Mitsuba's ``sunsky`` is z-up in its local frame, as the project's world; the map is
the project's equirect (``core.equirect``).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.equirect import equirect_directions, solid_angle_image

DEFAULT_TURBIDITY = 3.0     # a clear day (Hosek–Wilkie: 1 very clear … 10 hazy)
GROUND_ALBEDO = 0.2         # the model's ground albedo (its sky's brightening near the horizon)
MIN_ELEVATION_DEG = 0.5     # the model needs the sun above the horizon


def clear_sky(direction, height: int, width: int, turbidity: float = DEFAULT_TURBIDITY):
    """[height, width, 3] float64 equirect radiance of a clear sky (no sun disk) for a sun
    toward ``direction`` (world unit vector, z up; lifted to ``MIN_ELEVATION_DEG`` if
    lower), from Mitsuba's ``sunsky`` in its own units; zero below the horizon.
    ValueError for a non-finite direction or a turbidity outside [1, 10]."""
    d = np.asarray(direction, np.float64).reshape(3)
    if not np.isfinite(d).all() or np.linalg.norm(d) < 1e-9:
        raise ValueError(f"clear_sky: the sun's direction must be a finite non-zero vector, "
                         f"got {direction!r}")
    if not 1.0 <= float(turbidity) <= 10.0:
        raise ValueError(f"clear_sky: turbidity must be in [1, 10], got {turbidity!r}")
    d = d / np.linalg.norm(d)
    horiz = np.hypot(d[0], d[1])
    el = max(np.arcsin(np.clip(d[2], -1.0, 1.0)), np.radians(MIN_ELEVATION_DEG))
    az = np.arctan2(d[1], d[0]) if horiz > 1e-9 else 0.0
    d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    sky = mi.load_dict({"type": "sunsky", "sun_direction": mi.ScalarVector3f(*d),
                        "turbidity": float(turbidity), "albedo": GROUND_ALBEDO,
                        "sun_scale": 0.0})
    dirs = equirect_directions(height, width).reshape(-1, 3)
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = mi.Vector3f(*(-dirs[:, i] for i in range(3)))   # eval looks along -wi
    v = sky.eval(si)
    out = np.stack([np.asarray(v[i], np.float64) for i in range(3)], -1)
    out = np.where(dirs[:, 2:3] > 0.0, np.maximum(out, 0.0), 0.0)
    return out.reshape(height, width, 3)


def fill_unseen_sky(radiance_eq, unseen, direction, turbidity: float = DEFAULT_TURBIDITY):
    """(new equirect [H, W, 3] float64, the scale applied): the pixels ``unseen`` ([H, W]
    bool, above the horizon and not observed) replaced by :func:`clear_sky` for ``direction``,
    scaled so that their luminance irradiance on a surface facing up (Σ luminance × cos θ ×
    solid angle: what lights the ground, and what the sun is scaled by) is the one they
    had; every other pixel unchanged. Nothing unseen, or an unseen sky of zero luminance: the map
    unchanged and scale 0."""
    rad = np.array(radiance_eq, np.float64)
    h, w = rad.shape[:2]
    unseen = np.asarray(unseen, bool) & (equirect_directions(h, w)[..., 2] > 0.0)
    if not unseen.any():
        return rad, 0.0
    sa = solid_angle_image(h, w) * np.maximum(equirect_directions(h, w)[..., 2], 0.0)
    before = float(((rad @ LUMA) * sa)[unseen].sum())
    model = clear_sky(direction, h, w, turbidity)
    power = float(((model @ LUMA) * sa)[unseen].sum())
    if before <= 0.0 or power <= 0.0:
        return rad, 0.0
    scale = before / power
    rad[unseen] = scale * model[unseen]
    return rad, scale
