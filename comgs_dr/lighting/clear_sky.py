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
elevation and the air's turbidity through a physical model: Mitsuba's ``sunsky`` emitter
(Hosek and Wilkie's analytic sky), used here rather than a hand-written model. The
turbidity is read from the shadows too: they measure k, the sun's irradiance against the
sky's, and a hazier sky takes light from the sun (the model's k at sun elevations 10–70°:
5.5–5.9 at turbidity 3, 3.1–3.6 at 5, 0.3–0.9 at 10), so the turbidity is the one whose
model k is the fit's (:func:`turbidity_for`; the benchmark's sunrise: k 4.63 → 3.4, a
city map: 1.54 → 8.7).
The model supplies the shape and colour only: the unseen sky keeps the completion's
luminance irradiance on a surface facing up (the absolute level needs the ground's albedo,
which nothing measures), and observed pixels are never changed (the panorama keeps what it
saw). Measured on three scenes that never saw the sky (diffuse-sphere si-RMSE against the
light path-traced at the placement; the completion's sky / turbidity 3 / from k): the
composition benchmark under ``blender_sunrise`` 0.189 / 0.084 / 0.076, under
``blender_city`` 0.386 / 0.422 / 0.368, the demo's procedural sky 0.095 / 0.074 / 0.117
(docs/composite.md, "The unseen sky").

Frames: Mitsuba's ``sunsky`` is z-up in its local frame, as the project's world; the map is
the project's equirect (``core.equirect``).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.equirect import equirect_directions, resize_mask, solid_angle_image

DEFAULT_TURBIDITY = 3.0     # a clear day (Hosek–Wilkie: 1 very clear … 10 hazy)
TURBIDITIES = (1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0)   # searched by k
GROUND_ALBEDO = 0.2         # the model's ground albedo (its sky's brightening near the horizon)
MIN_ELEVATION_DEG = 0.5     # the model needs the sun above the horizon
MAX_GROUND_ALBEDO = 0.3     # E_down / E_up allowed before the unseen sky is raised: the
                            # 13 shared real maps' own ratio (brightest channel) has median
                            # 0.23, 11 of 13 ≤ 0.31 (benchmarks/ground_reflectance.py)
MAX_LIFT = 4.0              # ... by at most this factor (a few unseen pixels would else
                            # become a fake bright light; the city map needed 3.14)


def clear_sky(direction, height: int, width: int, turbidity: float = DEFAULT_TURBIDITY):
    """[height, width, 3] float64 equirect radiance of a clear sky (no sun disk) for a sun
    toward ``direction`` (world unit vector, z up; lifted to ``MIN_ELEVATION_DEG`` if
    lower), from Mitsuba's ``sunsky`` in its own units; zero below the horizon.
    ValueError for a non-finite direction or a turbidity outside [1, 10]."""
    sky, _ = _model(direction, turbidity, sun=False)
    dirs = equirect_directions(height, width).reshape(-1, 3)
    out = _eval(sky, dirs)
    out = np.where(dirs[:, 2:3] > 0.0, np.maximum(out, 0.0), 0.0)
    return out.reshape(height, width, 3)


def _model(direction, turbidity: float, sun: bool):
    """Mitsuba's ``sunsky`` for a sun toward ``direction`` (lifted to ``MIN_ELEVATION_DEG``):
    its sky only (``sun`` False) or its sun only."""
    d = np.asarray(direction, np.float64).reshape(3)
    if not np.isfinite(d).all() or np.linalg.norm(d) < 1e-9:
        raise ValueError(f"clear_sky: the sun's direction must be a finite non-zero vector, "
                         f"got {direction!r}")
    if not 1.0 <= float(turbidity) <= 10.0:
        raise ValueError(f"clear_sky: turbidity must be in [1, 10], got {turbidity!r}")
    d = d / np.linalg.norm(d)
    el = max(np.arcsin(np.clip(d[2], -1.0, 1.0)), np.radians(MIN_ELEVATION_DEG))
    az = np.arctan2(d[1], d[0]) if np.hypot(d[0], d[1]) > 1e-9 else 0.0
    d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return mi.load_dict({"type": "sunsky", "sun_direction": mi.ScalarVector3f(*d),
                         "turbidity": float(turbidity), "albedo": GROUND_ALBEDO,
                         "sun_scale": 1.0 if sun else 0.0, "sky_scale": 0.0 if sun else 1.0}), d


def _eval(emitter, dirs: np.ndarray) -> np.ndarray:
    """[N, 3] float64 radiance of ``emitter`` toward the unit directions ``dirs`` [N, 3]."""
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = mi.Vector3f(*(-dirs[:, i] for i in range(3)))     # eval looks along -wi
    v = emitter.eval(si)
    return np.stack([np.asarray(v[i], np.float64) for i in range(3)], -1)


def sun_sky_ratio(direction, turbidity: float, sky_res: int = 64, sun_samples: int = 41):
    """The model's luminance k = E_sun(facing the sun) / E_sky(facing up) for a sun toward
    ``direction`` at ``turbidity``: the quantity ``sun_fit`` measures from the shadows. The
    sky's irradiance on a [sky_res, 2 sky_res] equirect; the sun's over a square of
    ``sun_samples``² directions across its disk (0.27° radius). A hazier sky (higher
    turbidity) takes light from the sun: k 5.5–5.9 at turbidity 3, 3.1–3.6 at 5, 0.3–0.9
    at 10, over sun elevations 10–70° (the least at the lowest sun)."""
    sky, d = _model(direction, turbidity, sun=False)
    dirs = equirect_directions(sky_res, 2 * sky_res)
    cos = np.maximum(dirs[..., 2], 0.0) * solid_angle_image(sky_res, 2 * sky_res)
    e_sky = float((_eval(sky, dirs.reshape(-1, 3)) @ LUMA) @ cos.reshape(-1))
    sun, _ = _model(direction, turbidity, sun=True)
    t1 = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(d, t1)
    a = np.radians(0.35)
    g = np.linspace(-a, a, sun_samples)
    u, v = np.meshgrid(g, g)
    q = d + u.reshape(-1, 1) * t1 + v.reshape(-1, 1) * t2
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    e_sun = float((_eval(sun, q) @ LUMA).sum() * (g[1] - g[0]) ** 2)
    return e_sun / max(e_sky, 1e-300)


def turbidity_for(direction, k: float) -> float:
    """The turbidity in [1.5, 10] at which the model's sun/sky ratio (:func:`sun_sky_ratio`)
    is ``k`` (luminance E_sun(facing) / E_sky(up), as the shadows measured it),
    interpolated in log k over ``TURBIDITIES``; clamped at the ends. The shadows' contrast
    says how hazy the sky is: a clear sky is blue, a hazy one whiter and brighter."""
    if not np.isfinite(k) or k <= 0:
        return TURBIDITIES[-1]
    r = np.log([sun_sky_ratio(direction, t) for t in TURBIDITIES])      # falls with T
    return float(np.interp(-np.log(k), -r, TURBIDITIES))


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


def ground_albedo_floor(radiance_eq, unseen, k_rgb, sun_elevation: float,
                        max_albedo: float = MAX_GROUND_ALBEDO):
    """(new equirect [H, W, 3] float64, the scale s ≥ 1 applied to the ``unseen`` pixels, the
    implied albedo per channel before): the unseen sky raised until what the ground
    reflects is physically plausible.

    The panorama measured the surroundings below the horizon; their irradiance on a surface
    facing down, E_down, is what the ground reflects: for a Lambertian ground E_down = ρ ·
    E_up, ρ its albedo. The completion's level for a sky nobody saw can imply ρ > 1: the
    composition benchmark's scene under ``blender_city`` had E_down / E_up 1.51, 0.98, 0.56
    (the truth's 0.27, 0.21, 0.14; the ground reflecting half again the light it receives),
    the demo's scene without sky views 0.73, 0.46, 0.36 (truth 0.27, 0.21, 0.14). The
    unseen pixels (and with them the sun to be added, ``k_rgb`` × the sky's E_up at
    ``sun_elevation`` radians) are scaled by the least s that brings every channel to
    ``max_albedo`` (0.3: what real maps' surroundings reflect, median 0.23 over the 13
    shared maps, 11 of them ≤ 0.31; grass, soil, asphalt and concrete reflect 0.1–0.35; a
    sunlit courtyard (0.52), a bright interior floor (0.58), fresh snow or white sand are
    then lit too brightly when their sky was unseen); never
    lowered, and raised by at most ``MAX_LIFT``: when little of the sky is unseen, scaling it
    further would turn those few pixels into a bright light nobody saw. Zero
    ``max_albedo``, nothing unseen or no light above: unchanged (s = 1)."""
    rad = np.array(radiance_eq, np.float64)
    h, w = rad.shape[:2]
    dirs = equirect_directions(h, w)
    sa = solid_angle_image(h, w)
    unseen = np.asarray(unseen, bool) & (dirs[..., 2] > 0.0)
    up = sa * np.maximum(dirs[..., 2], 0.0)
    e_down = np.einsum("hwc,hw->c", rad, sa * np.maximum(-dirs[..., 2], 0.0))
    e_seen = np.einsum("hwc,hw->c", rad * ~unseen[..., None], up)
    e_unseen = np.einsum("hwc,hw->c", rad * unseen[..., None], up)
    sun = 1.0 + np.asarray(k_rgb, np.float64) * max(np.sin(sun_elevation), 0.0)
    total = (e_seen + e_unseen) * sun
    implied = e_down / np.maximum(total, 1e-300)
    if max_albedo <= 0 or not unseen.any() or not (e_unseen > 0).all():
        return rad, 1.0, implied
    need = (e_down / (max_albedo * sun) - e_seen) / e_unseen
    s = float(np.clip(need.max(), 1.0, MAX_LIFT))
    rad[unseen] *= s
    return rad, s, implied


def lift_unseen_sky(radiance_eq, observed, max_albedo: float = MAX_GROUND_ALBEDO):
    """(new equirect [H, W, 3] float64, the lift s, the implied albedo per channel before)
    for a panorama that gets no sun from the shadows: its unseen sky (above the horizon and
    not ``observed`` [h, w] bool, resized nearest to the map) raised by
    :func:`ground_albedo_floor` without a sun (k = 0). The completion's level for a sky
    nobody saw was 1.2–5.6× too dim on every outdoor scene measured (docs/composite.md),
    also where the sun was too low for a usable shadow."""
    rad = np.asarray(radiance_eq, np.float64)
    obs = resize_mask(observed, *rad.shape[:2])
    return ground_albedo_floor(rad, ~obs, np.zeros(3), 0.0, max_albedo)
