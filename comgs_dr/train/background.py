"""A learned environment behind the surfels of step 1 (sky and far field).

Outdoor captures see the sky, which no surfel at a finite depth can hold: without a
background model its pixels are fitted by hazy floaters (or left black) and the lighting
estimation at a placement later finds a hole exactly where the sun and the sky are. Here
the colour of a camera ray is C + T_final · E(d), with E an ``octenvmap`` (octahedral,
bilinear) learned with the surfels by the same Adam step (``surfel_gbuffer`` with
``env_background``), as 3DGS trainers of unbounded scenes add a sky or background model.

E holds the radiance field's own display values (the training images' space), not linear
radiance. After training, :func:`observed_fraction` records for every texel the largest
transmittance T_final of the training rays that reached it: texels seen only through
opaque surfels, or never, are not observed and are left to the completion network.

The captures are LDR: a sun or lamp is stored at the white level in one or two pixels, and
the fit (TV-smoothed, [0, 1], texels larger than those pixels) averages it with the sky
around it, below white (``benchmarks/recon_light_e2e.py``: blender_sunrise's sun came back
at 0.954, no clipped region was found at the placement and the sun's power was lost:
E(sun)/E(up) −61 %). :func:`capture_maps` therefore also records, per texel and channel,
whether a training ray that reached it with T_final ≥ ½ saw a *clipped* pixel (≥ ``CLIPPED``
in that channel); the placement's panorama shows those texels at white, so the light head
finds the light there (``surfels.panorama.composite_background``).

Files: ``background.exr`` (octahedral RGB, ``layout`` metadata),
``background_observed.exr`` (the observed fraction, grey) and ``background_clipped.exr``
(per channel, the largest T_final of a ray that saw the channel clipped) in the run folder.
"""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core import exr
from comgs_dr.core import octahedral as octa
from comgs_dr.core.cameras import camera_rays
from comgs_dr.emitters.octenvmap import emitter_class
from comgs_dr.lighting.envmap import read_envmap_file, write_exr

KEY = "environment.data"
FILE, OBSERVED_FILE = "background.exr", "background_observed.exr"
CLIPPED_FILE = "background_clipped.exr"
CLIPPED = 0.98      # a display value at/above this is clipped (as ``lighting.lights.SAT``)


def initial_emitter(resolution: int, views) -> "mi.Emitter":
    """An ``octenvmap`` of ``resolution``² texels holding the mean colour of the training
    images (a neutral start: the first steps do not push surfels to explain a black sky)."""
    if resolution < 4:
        raise ValueError(f"background: the octahedral resolution must be >= 4, got {resolution}")
    mean = np.mean([np.asarray(v.image[..., :3], np.float64).reshape(-1, 3).mean(0)
                    for v in views], 0)                                      # [3]
    return emitter_class().from_radiance(np.broadcast_to(mean, (resolution, resolution, 3)),
                                         id="environment")


def clamp(opt) -> None:
    """Keep the learned values in [0, 1], the range of the (LDR, display-valued) training
    images. Above 1 the background would only compensate for half-transparent floaters in
    front of the sky, and such texels read as clipped lights at the placement."""
    opt[KEY] = dr.clip(opt[KEY], 0.0, 1.0)


def total_variation(data) -> "mi.Float":
    """Mean |Δ| between neighbouring texels of the [R, R, 3] map (anisotropic TV, L1 keeps
    the sun's edge). Texels that few rays touch, and only with small bilinear weights, were
    pushed to extremes by the photometric loss alone (a sky texel at blue = 1 read as a
    clipped light at the placement); Adam normalises every texel's step, so for them this
    term decides and smooths them towards their neighbours."""
    t = data if isinstance(data, mi.TensorXf) else mi.TensorXf(data)
    dx = dr.abs(t[:, 1:, :] - t[:, :-1, :])
    dy = dr.abs(t[1:, :, :] - t[:-1, :, :])
    return (dr.mean(dx.array) + dr.mean(dy.array)) * 0.5


def observed_fraction(scene, integ, sensors: list[int], resolution: int) -> np.ndarray:
    """[R, R] largest T_final of the camera rays of ``sensors`` whose bilinear lookup
    touches each texel (every texel the fit could move).

    ``scene`` renders ``color`` and ``weight`` (T_final = 1 − W) with the ``surfel_gbuffer``
    integrator ``integ``; rays are the integrator's own (pixel centres)."""
    return capture_maps(scene, integ, sensors, resolution)[0]


def capture_maps(scene, integ, sensors: list[int], resolution: int, images=None,
                 clipped: float = CLIPPED) -> tuple[np.ndarray, np.ndarray | None]:
    """(observed [R, R], clipped [R, R, 3] or None): :func:`observed_fraction`, and with
    ``images`` (the sensors' display images [H, W, 3]) per texel and channel the largest
    T_final of a ray whose pixel is ≥ ``clipped`` in that channel. The clipped record goes
    to the ray's nearest texel only (not the bilinear footprint): a one-pixel sun stays one
    texel, not four."""
    obs = np.zeros(resolution * resolution, np.float64)
    clip = None if images is None else np.zeros((resolution * resolution, 3), np.float64)
    for k, i in enumerate(sensors):
        sensor = scene.sensors()[i]
        img = mi.render(scene, sensor=i)
        T = np.clip(1.0 - np.asarray(integ.split(img)["weight"], np.float64).reshape(-1),
                    0.0, 1.0)                                                     # [P]
        dirs, _ = camera_rays(sensor)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)                             # [P, 3]
        x = octa.dir_to_uv_np(d) * resolution - 0.5                               # [P, 2]
        x0 = np.floor(x).astype(np.int64)
        for dx in (0, 1):                  # every texel of the pixel's bilinear footprint
            for dy in (0, 1):
                i = np.clip(x0[:, 0] + dx, 0, resolution - 1)
                j = np.clip(x0[:, 1] + dy, 0, resolution - 1)
                np.maximum.at(obs, j * resolution + i, T)
        if clip is not None:
            im = np.asarray(images[k], np.float64)[..., :3].reshape(-1, 3)          # [P, 3]
            if len(im) != len(T):
                raise ValueError(f"capture_maps: image {k} has {len(im)} pixels, its sensor "
                                 f"renders {len(T)}")
            n = np.clip(np.floor(x + 0.5).astype(np.int64), 0, resolution - 1)    # nearest
            hit = (im >= clipped) * T[:, None]                                    # [P, 3]
            np.maximum.at(clip, n[:, 1] * resolution + n[:, 0], hit)
    return (obs.reshape(resolution, resolution),
            None if clip is None else clip.reshape(resolution, resolution, 3))


def save(run_dir, radiance: np.ndarray, observed: np.ndarray,
         clipped: np.ndarray | None = None) -> tuple[Path, ...]:
    """Write ``background.exr`` (octahedral [R, R, 3]), ``background_observed.exr`` and,
    when given, ``background_clipped.exr`` ([R, R, 3])."""
    run_dir = Path(run_dir)
    a = write_exr(run_dir / FILE, np.asarray(radiance, np.float32), "octahedral")
    b = exr.write_image(run_dir / OBSERVED_FILE,
                        np.repeat(np.asarray(observed, np.float32)[..., None], 3, -1),
                        {"layout": "octahedral", "content": "observed fraction (max T_final)"})
    if clipped is None:
        return a, b
    clipped = np.asarray(clipped, np.float32)
    if clipped.shape != np.shape(radiance):
        raise ValueError(f"background.save: clipped {clipped.shape} does not match the "
                         f"background {np.shape(radiance)}")
    c = exr.write_image(run_dir / CLIPPED_FILE, clipped,
                        {"layout": "octahedral", "content": "clipped fraction (max T_final "
                         f"of a ray whose pixel is >= {CLIPPED}, per channel)"})
    return a, b, c


def load(run_dir) -> tuple[np.ndarray, np.ndarray] | None:
    """(radiance [R, R, 3], observed [R, R]) of a run folder, or None if it has none.
    ValueError when the files are inconsistent or hold non-finite values."""
    run_dir = Path(run_dir)
    if not (run_dir / FILE).is_file():
        return None
    rad, layout = read_envmap_file(run_dir / FILE)
    if layout != "octahedral" or rad.shape[0] != rad.shape[1]:
        raise ValueError(f"{run_dir / FILE}: expected an octahedral [R, R, 3] map, got "
                         f"{layout} {rad.shape}")
    if not (run_dir / OBSERVED_FILE).is_file():
        raise ValueError(f"{run_dir / FILE} has no {OBSERVED_FILE} beside it (which texels "
                         "the cameras saw); re-run step 1 or delete the background")
    obs = np.asarray(exr.read_image(run_dir / OBSERVED_FILE), np.float64)[..., 0]
    if obs.shape != rad.shape[:2]:
        raise ValueError(f"{run_dir / OBSERVED_FILE}: shape {obs.shape} does not match the "
                         f"background's {rad.shape[:2]}")
    for name, a in ((FILE, rad), (OBSERVED_FILE, obs)):
        if not np.isfinite(a).all():
            raise ValueError(f"{run_dir / name} holds {int((~np.isfinite(a)).sum())} non-finite "
                             "values")
    return np.maximum(rad, 0.0), np.clip(obs, 0.0, 1.0)


def load_clipped(run_dir) -> np.ndarray | None:
    """The clipped record [R, R, 3] in [0, 1] of a run folder (:func:`capture_maps`), or None
    for runs written before it existed. ValueError for non-finite values or a shape that
    does not match ``background.exr``."""
    run_dir = Path(run_dir)
    if not (run_dir / CLIPPED_FILE).is_file():
        return None
    c = np.asarray(exr.read_image(run_dir / CLIPPED_FILE), np.float64)[..., :3]
    if not np.isfinite(c).all():
        raise ValueError(f"{run_dir / CLIPPED_FILE} holds {int((~np.isfinite(c)).sum())} "
                         "non-finite values")
    if (run_dir / FILE).is_file():
        rad = read_envmap_file(run_dir / FILE)[0]
        if c.shape != rad.shape:
            raise ValueError(f"{run_dir / CLIPPED_FILE}: shape {c.shape} does not match the "
                             f"background's {rad.shape}")
    return np.clip(c, 0.0, 1.0)
