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
around it, below white: the placement's panorama would then hold no clipped region and
the sun's power would be lost. :func:`capture_maps` therefore also records
the rays that saw the open sky (T_final ≥ ½) *clipped* (≥ ``CLIPPED`` in a channel): their
directions, channels and pixel sizes. The placement's panorama shows those directions at
white, so the light head finds the light there (``surfels.panorama.composite_background``).

Files: ``background.exr`` (octahedral RGB, ``layout`` metadata),
``background_observed.exr`` (the observed fraction, grey) and ``background_clipped.npz``
(the clipped record) in the run folder.
"""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core import exr
from comgs_dr.core import octahedral as octa
from comgs_dr.core.cameras import camera_rays
from comgs_dr.core.hostarray import to_jit
from comgs_dr.emitters.octenvmap import emitter_class
from comgs_dr.lighting.envmap import read_envmap_file, write_exr
from comgs_dr.lighting.hdr import SAT

KEY = "environment.data"
FILE, OBSERVED_FILE = "background.exr", "background_observed.exr"
CLIPPED_FILE = "background_clipped.npz"
CLIPPED = SAT       # a display value at/above this is clipped (``lighting.hdr.SAT``)


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
    the sun's edge). Texels that few rays touch, and only with small bilinear weights, are
    pushed to extremes by the photometric loss alone (a sky texel at blue = 1 reads as a
    clipped light at the placement); Adam normalises every texel's step, so for them this
    term decides and smooths them towards their neighbours."""
    t = data if isinstance(data, mi.TensorXf) else to_jit(mi.TensorXf, data)
    dx = dr.abs(t[:, 1:, :] - t[:, :-1, :])
    dy = dr.abs(t[1:, :, :] - t[:-1, :, :])
    return (dr.mean(dx.array) + dr.mean(dy.array)) * 0.5


def observed_fraction(scene, integ, sensors: list[int], resolution: int) -> np.ndarray:
    """[R, R] largest T_final of the camera rays of ``sensors`` whose bilinear lookup
    touches each texel (every texel the fit could move).

    ``scene`` renders ``color`` and ``weight`` (T_final = 1 − W) with the ``surfel_gbuffer``
    integrator ``integ``; rays are the integrator's own (pixel centres)."""
    return capture_maps(scene, integ, sensors, resolution)[0]


def pixel_radius(dirs) -> np.ndarray:
    """[H, W] angular radius (rad) of a disc with each pixel's solid angle, from the ray
    directions ``dirs`` [H, W, 3] through the pixel centres: the angles to the next pixel
    across and down give the pixel's sides a, b, and r = sqrt(a·b/π) (equal area)."""
    d = np.asarray(dirs, np.float64)
    def ang(u, v):
        return np.arccos(np.clip((u * v).sum(-1), -1.0, 1.0))
    a = ang(d[:, 1:], d[:, :-1])                                            # [H, W-1]
    b = ang(d[1:], d[:-1])                                                  # [H-1, W]
    a = np.concatenate([a, a[:, -1:]], 1) if a.shape[1] else np.full(d.shape[:2], np.pi)
    b = np.concatenate([b, b[-1:]], 0) if b.shape[0] else a
    return np.sqrt(a * b / np.pi)


def capture_maps(scene, integ, sensors: list[int], resolution: int, images=None,
                 clipped: float = CLIPPED, masks=None) -> tuple[np.ndarray, dict | None]:
    """(observed [R, R], record or None): :func:`observed_fraction`, and with ``images``
    (the sensors' display images [H, W, 3]) the record of every ray that saw the open sky
    (T_final ≥ ½) clipped: {"directions" [M, 3], "channels" [M, 3] (1 where ≥ ``clipped``),
    "weight" [M] (T_final), "radius" [M] (the pixel's equal-area angular radius, rad)}.

    Rays, not texels: a one-pixel sun stays the size of a capture pixel whatever the
    background's resolution (a texel record would make it as large as a texel, several
    times the sun's solid angle, and the light head reads a region's size).

    ``masks`` (per sensor [H, W] alpha, or None): a transparent pixel shows no sky, so a ray
    counts as T_final × alpha: a capture rendered with the sky hidden (alpha 0 there) teaches
    the background black, and counted as seen it would put a sky at the placement that no
    image showed (and that the completion would never fill)."""
    obs = np.zeros(resolution * resolution, np.float64)
    rec = None if images is None else {"directions": [], "channels": [], "weight": [],
                                       "radius": []}
    for k, i in enumerate(sensors):
        sensor = scene.sensors()[i]
        img = mi.render(scene, sensor=i)
        T = np.clip(1.0 - np.asarray(integ.split(img)["weight"], np.float64).reshape(-1),
                    0.0, 1.0)                                                     # [P]
        if masks is not None and masks[k] is not None:
            a = np.clip(np.asarray(masks[k], np.float64).reshape(-1), 0.0, 1.0)   # [P]
            if len(a) != len(T):
                raise ValueError(f"capture_maps: mask {k} has {len(a)} pixels, its sensor "
                                 f"renders {len(T)}")
            T = T * a
        dirs, _ = camera_rays(sensor)
        grid = np.asarray(dirs, np.float64)                                         # [H, W, 3]
        d = grid.reshape(-1, 3)                                                     # [P, 3]
        x = octa.dir_to_uv_np(d) * resolution - 0.5                               # [P, 2]
        x0 = np.floor(x).astype(np.int64)
        for dx in (0, 1):                  # every texel of the pixel's bilinear footprint
            for dy in (0, 1):
                i = np.clip(x0[:, 0] + dx, 0, resolution - 1)
                j = np.clip(x0[:, 1] + dy, 0, resolution - 1)
                np.maximum.at(obs, j * resolution + i, T)
        if rec is not None:
            im = np.asarray(images[k], np.float64)[..., :3].reshape(-1, 3)          # [P, 3]
            if len(im) != len(T):
                raise ValueError(f"capture_maps: image {k} has {len(im)} pixels, its sensor "
                                 f"renders {len(T)}")
            ch = im >= clipped                                                    # [P, 3]
            sel = ch.any(-1) & (T >= 0.5)
            rec["directions"].append(d[sel])
            rec["channels"].append(ch[sel])
            rec["weight"].append(T[sel])
            rec["radius"].append(pixel_radius(grid).reshape(-1)[sel])
    if rec is not None:
        rec = {"directions": np.concatenate(rec["directions"]).reshape(-1, 3).astype(np.float32),
               "channels": np.concatenate(rec["channels"]).reshape(-1, 3).astype(np.uint8),
               "weight": np.concatenate(rec["weight"]).astype(np.float32),
               "radius": np.concatenate(rec["radius"]).astype(np.float32)}
    return obs.reshape(resolution, resolution), rec


def splat_record(rec: dict, h: int, w: int) -> np.ndarray:
    """[H, W, 3] equirect map of a clipped record (:func:`capture_maps`): per channel the
    largest weight of a recorded ray whose disc (its pixel's radius) holds the pixel's
    centre, and every ray also marks the pixel it falls in (a panorama coarser than the
    capture still shows it). Discs are tested against the nearest recorded ray only (all
    rays of a capture have about the same radius); ``scipy.spatial.cKDTree`` finds it."""
    from scipy.spatial import cKDTree

    from comgs_dr.core.equirect import equirect_dir_to_uv_np, equirect_directions
    out = np.zeros((h * w, 3), np.float64)
    d = np.asarray(rec["directions"], np.float64)
    if len(d) == 0:
        return out.reshape(h, w, 3)
    val = np.asarray(rec["channels"], np.float64) * np.asarray(rec["weight"], np.float64)[:, None]
    pix = equirect_directions(h, w).reshape(-1, 3)                               # [H*W, 3]
    rad = np.asarray(rec["radius"], np.float64)
    chord = 2.0 * np.sin(np.minimum(rad, np.pi) / 2.0)                           # [M]
    dist, idx = cKDTree(d).query(pix, k=1, distance_upper_bound=float(chord.max()))
    hit = np.isfinite(dist)
    hit[hit] = dist[hit] <= chord[idx[hit]]
    out[hit] = val[idx[hit]]
    uv = np.asarray(equirect_dir_to_uv_np(d), np.float64)                           # [M, 2]
    px = np.clip((uv[:, 0] * w).astype(np.int64), 0, w - 1)
    py = np.clip((uv[:, 1] * h).astype(np.int64), 0, h - 1)
    np.maximum.at(out, py * w + px, val)
    return out.reshape(h, w, 3)


def save(run_dir, radiance: np.ndarray, observed: np.ndarray,
         clipped: dict | None = None) -> tuple[Path, ...]:
    """Write ``background.exr`` (octahedral [R, R, 3]), ``background_observed.exr`` and,
    when given, the clipped record (:func:`capture_maps`) as ``background_clipped.npz``."""
    run_dir = Path(run_dir)
    a = write_exr(run_dir / FILE, np.asarray(radiance, np.float32), "octahedral")
    b = exr.write_image(run_dir / OBSERVED_FILE,
                        np.repeat(np.asarray(observed, np.float32)[..., None], 3, -1),
                        {"layout": "octahedral",
                         "content": "observed fraction (max T_final x alpha)"})
    if clipped is None:
        return a, b
    rec = _check_record(clipped, "background.save")
    np.savez_compressed(run_dir / CLIPPED_FILE, level=np.float32(CLIPPED), **rec)
    return a, b, run_dir / CLIPPED_FILE


def _check_record(rec, where: str) -> dict:
    try:
        out = {"directions": np.asarray(rec["directions"], np.float32).reshape(-1, 3),
               "channels": np.asarray(rec["channels"], np.uint8).reshape(-1, 3),
               "weight": np.asarray(rec["weight"], np.float32).reshape(-1),
               "radius": np.asarray(rec["radius"], np.float32).reshape(-1)}
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{where}: a clipped record needs directions [M, 3], channels "
                         f"[M, 3], weight [M] and radius [M] ({exc})") from exc
    m = len(out["directions"])
    if any(len(v) != m for v in out.values()):
        raise ValueError(f"{where}: clipped record arrays differ in length: "
                         f"{ {k: len(v) for k, v in out.items()} }")
    bad = sum(int((~np.isfinite(v)).sum()) for k, v in out.items() if k != "channels")
    if bad:
        raise ValueError(f"{where}: the clipped record holds {bad} non-finite values")
    if m and (out["radius"].min() <= 0 or out["radius"].max() > np.pi):
        raise ValueError(f"{where}: clipped record radii must be in (0, pi] rad")
    n = np.linalg.norm(out["directions"], axis=1)
    if m and np.abs(n - 1.0).max() > 1e-3:
        raise ValueError(f"{where}: clipped record directions must be unit vectors")
    return out


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


def load_clipped(run_dir) -> dict | None:
    """The clipped record of a run folder (:func:`capture_maps`), or None for runs written
    before it existed. ValueError for a malformed record."""
    path = Path(run_dir) / CLIPPED_FILE
    if not path.is_file():
        return None
    with np.load(path) as z:
        return _check_record({k: z[k] for k in z.files if k != "level"}, str(path))
