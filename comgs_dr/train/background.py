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
Files: ``background.exr`` (octahedral RGB, ``layout`` metadata) and
``background_observed.exr`` (the observed fraction, grey) in the run folder.
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
    obs = np.zeros(resolution * resolution, np.float64)
    for i in sensors:
        sensor = scene.sensors()[i]
        img = mi.render(scene, sensor=i)
        T = 1.0 - np.asarray(integ.split(img)["weight"], np.float64).reshape(-1)     # [P]
        dirs, _ = camera_rays(sensor)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)                             # [P, 3]
        x = octa.dir_to_uv_np(d) * resolution - 0.5                               # [P, 2]
        x0 = np.floor(x).astype(np.int64)
        for dx in (0, 1):                  # every texel of the pixel's bilinear footprint
            for dy in (0, 1):
                i = np.clip(x0[:, 0] + dx, 0, resolution - 1)
                j = np.clip(x0[:, 1] + dy, 0, resolution - 1)
                np.maximum.at(obs, j * resolution + i, np.clip(T, 0.0, 1.0))
    return obs.reshape(resolution, resolution)


def save(run_dir, radiance: np.ndarray, observed: np.ndarray) -> tuple[Path, Path]:
    """Write ``background.exr`` (octahedral [R, R, 3]) and ``background_observed.exr``."""
    run_dir = Path(run_dir)
    a = write_exr(run_dir / FILE, np.asarray(radiance, np.float32), "octahedral")
    b = exr.write_image(run_dir / OBSERVED_FILE,
                        np.repeat(np.asarray(observed, np.float32)[..., None], 3, -1),
                        {"layout": "octahedral", "content": "observed fraction (max T_final)"})
    return a, b


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
