"""Training and evaluation data for panorama completion (Appendix "Training Dataset").

The paper pairs HDR environment maps (Poly Haven, Laval, Text2Light) with coverage masks traced
from reconstructed Gaussian scenes with *random-region dropout*. Nothing can be downloaded here,
so the package makes its own:

* **HDR panoramas** (equirect, Z-up, linear, the ``lighting.envmap`` convention):
  ``load_map`` (any .hdr/.exr, area-downsampled so a small sun keeps its power),
  ``sunsky_panorama`` (Mitsuba's ``sunsky`` sky + sun splatted with its exact power + a
  Lambertian ground and a procedural skyline lit by that sky; label outdoor) and
  ``room_panorama`` (a procedural room with ceiling lamps, bright windows and furniture, path
  traced by Mitsuba from a point inside; label indoor).
* **Masks** live in :mod:`comgs_dr.data.pano_masks` (they are traced surfel panoramas).
* ``auto_exposure``: the scale that puts a map's log-average luminance at the key 0.18
  (Reinhard), used by training and evaluation to set the EV-0 exposure of the "capture".
"""
from __future__ import annotations

import colorsys
import json
import logging
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.equirect import (
    equirect_dir_to_uv_np,
    equirect_directions,
    pixel_directions,
    solid_angle_image,
)
from comgs_dr.core.hostarray import to_jit
from comgs_dr.lighting.envmap import read_envmap_file
from comgs_dr.lighting.hdr import area_resize_equirect, expose

log = logging.getLogger(__name__)

__all__ = ["HELD_OUT", "label_of", "trained_maps", "auto_exposure", "load_map", "load_maps",
           "map_files", "sunsky_panorama", "room_panorama", "rotate_u", "augmented_view"]

# evaluation maps of shared/data/hdri, never trained on: two Poly Haven maps and three of the
# Blender maps (blender_sunrise, the only shared map with a clear sun, is also the end-to-end
# test's sky)
HELD_OUT = ("forest_slope_1k", "st_fagans_interior_1k", "blender_sunrise", "blender_interior",
            "blender_courtyard")
INDOOR_HINTS = ("interior", "warehouse", "room", "indoor", "studio", "hall", "office")
GENERATOR_VERSION = 2      # bump when a generator's output changes (training-data cache key)
KEY = 0.18


def label_of(name: str) -> str:
    """'indoor' or 'outdoor' from a map's file stem (``INDOOR_HINTS``)."""
    return "indoor" if any(h in name.lower() for h in INDOOR_HINTS) else "outdoor"


def auto_exposure(hdr: np.ndarray, key: float = KEY) -> float:
    """Scale k so that the solid-angle-weighted log-average luminance of k·hdr is ``key``."""
    hdr = np.asarray(hdr, np.float64)
    if hdr.ndim != 3 or hdr.shape[-1] != 3:
        raise ValueError(f"auto_exposure: need an equirect [H, W, 3] map, got {hdr.shape}")
    if not np.all(np.isfinite(hdr)):
        raise ValueError("auto_exposure: the map holds NaN/Inf values")
    w = solid_angle_image(*hdr.shape[:2])                                   # [H, W]
    lum = np.maximum(hdr @ LUMA, 0.0)
    if lum.max() <= 0:
        raise ValueError("auto_exposure: the map is black")
    logavg = np.exp((w * np.log(lum + 1e-4 * lum.max())).sum() / w.sum())
    return float(key / logavg)


def load_map(path, h: int, w: int) -> np.ndarray:
    """An equirect HDR file resampled to [h, w, 3] (``hdr.area_resize_equirect``: power kept)."""
    img, layout = read_envmap_file(path)
    if layout != "equirect":
        raise ValueError(f"{path}: an equirect map is needed, got layout {layout!r}")
    img = np.asarray(img, np.float32)[..., :3]
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{path}: the map holds NaN/Inf values")
    return area_resize_equirect(np.maximum(img, 0.0), h, w).astype(np.float32)


def load_maps(paths, load, who: str) -> dict:
    """{path: load(path)} for every path, each checked (finite, not all black); one ValueError
    naming every map that cannot be used (unreadable, wrong layout, NaN/Inf, black), so that a
    run fails before its work, not minutes into it at the first bad file."""
    out, bad = {}, []
    for p in paths:
        try:
            m = np.asarray(load(p))
            if not np.isfinite(m).all():
                raise ValueError("the map holds NaN/Inf values")
            if not (m > 0).any():
                raise ValueError("the map is black (no light)")
            out[p] = m
        except (ValueError, OSError) as e:
            bad.append(f"{Path(p).name}: {e}")
    if bad:
        raise ValueError(f"{who}: {len(bad)} of {len(paths)} maps cannot be used (fix or move "
                         "them):\n  " + "\n  ".join(bad))
    return out


def map_files(folder, exclude=(), check_rows: int = 16) -> list:
    """The .hdr/.exr maps of ``folder`` (sorted paths; stems in ``exclude`` left out), each
    read once at ``check_rows`` rows by ``load_maps`` (a training run fails at once, naming
    every map it cannot use)."""
    files = sorted(p for p in Path(folder).glob("*")
                   if p.suffix.lower() in (".hdr", ".exr") and p.stem not in set(exclude))
    load_maps(files, lambda p: load_map(p, check_rows, 2 * check_rows), str(folder))
    return files


def trained_maps(path) -> frozenset | None:
    """The real maps (file stems) a lighting model was fitted on, from its model card: the
    JSON beside a ``.pt`` (``train-completion``: ``data.poly_haven``, plus ``data.init_maps``,
    those of the ``--init`` weights it was fine-tuned from; ``train-light-head``: ``maps``)
    or the ``train-scene-label`` model itself (``info.maps``). None when there is no card or
    it does not say (a model saved by hand). Evaluation on a map in this set is not a
    held-out score."""
    p = Path(path)
    card = p if p.suffix.lower() == ".json" else p.with_suffix(".json")
    try:
        d = json.loads(card.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(d, dict):
        return None
    for keys in (("data", "poly_haven"), ("maps",), ("info", "maps")):
        v = d
        for k in keys:
            v = v.get(k) if isinstance(v, dict) else None
        if isinstance(v, list) and all(isinstance(x, str) for x in v):
            init = d.get("data", {}).get("init_maps") if keys[0] == "data" else None
            extra = init if isinstance(init, list) and all(isinstance(x, str) for x in init) \
                else []
            return frozenset(v) | frozenset(extra)
    return None


def rotate_u(img: np.ndarray, shift: int) -> np.ndarray:
    """Rotation about +Z by ``shift`` pixels (a circular roll along u)."""
    return np.roll(img, int(shift), axis=1)


def augmented_view(rng: np.random.Generator, hdr: np.ndarray, k: float, masks,
                   aug_ev: float, wb_jitter: float, full_view: float):
    """One training draw of an HDR panorama [h, w, 3] as a capture sees it: rotated about Z,
    mirrored half the time, white-balanced (log-normal gains of σ ``wb_jitter``, luminance
    kept), exposed by ``k`` × 2^U(−aug_ev, aug_ev), and observed fully (probability
    ``full_view``) or through one of ``masks`` ([h', 2h'] alphas, pixel-repeated to h when
    h' divides it, rotated). Returns (radiance [h, w, 3], alpha [h, w], EV-0 LDR [h, w, 3],
    0 outside the mask). The light head's and the scene label's training share it."""
    h, w = hdr.shape[:2]
    m = rotate_u(hdr, rng.integers(w))
    m = m[:, ::-1] if rng.random() < 0.5 else m
    g = np.exp(rng.normal(0.0, wb_jitter, 3))
    m = m * k * 2.0 ** rng.uniform(-aug_ev, aug_ev) * (g / (g @ LUMA))
    if rng.random() < full_view:
        a = np.ones((h, w))
    else:
        a = masks[rng.integers(len(masks))]
        rep = max(h // a.shape[0], 1)
        a = rotate_u(np.repeat(np.repeat(a, rep, 0), rep, 1)[:h, :w], rng.integers(w))
    return m, a, np.where(a[..., None] > 0.5, expose(m, 0.0), 0.0)


def _splat_direction(img: np.ndarray, d: np.ndarray, power: np.ndarray) -> None:
    """Add ``power`` [3] (radiance × solid angle) at direction ``d`` to img [H, W, 3] with
    bilinear weights, dividing by each pixel's solid angle (energy preserving)."""
    H, W = img.shape[:2]
    uv = equirect_dir_to_uv_np(d[None])[0]
    x, y = uv[0] * W - 0.5, uv[1] * H - 0.5
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - x0, y - y0
    sa = solid_angle_image(H, W)
    for dy, wy in ((0, 1 - fy), (1, fy)):
        yy = min(max(y0 + dy, 0), H - 1)
        for dx, wx in ((0, 1 - fx), (1, fx)):
            xx = (x0 + dx) % W
            img[yy, xx] += wx * wy * power / sa[yy, xx]


def _eval_emitter(emitter, dirs: np.ndarray) -> np.ndarray:
    si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
    si.wi = to_jit(mi.Vector3f, -dirs.T)
    return np.asarray(emitter.eval(si), np.float64).T


def _fbm(rng, h: int, w: int, octaves: int = 4) -> np.ndarray:
    """Tileable-in-u value noise in [0, 1], [h, w]."""
    out = np.zeros((h, w))
    amp, tot = 1.0, 0.0
    for o in range(octaves):
        gh, gw = 2 + 2 ** o, 4 * 2 ** o
        g = rng.random((gh, gw))
        y = np.linspace(0, gh - 1, h)
        x = np.arange(w) * gw / w
        y0 = np.floor(y).astype(int).clip(0, gh - 2)
        x0 = np.floor(x).astype(int)
        fy, fx = (y - y0)[:, None], (x - x0)[None]
        a = g[y0][:, x0 % gw] * (1 - fx) + g[y0][:, (x0 + 1) % gw] * fx
        b = g[y0 + 1][:, x0 % gw] * (1 - fx) + g[y0 + 1][:, (x0 + 1) % gw] * fx
        out += amp * (a * (1 - fy) + b * fy)
        tot += amp
        amp *= 0.5
    return out / tot


def sunsky_panorama(rng: np.random.Generator, h: int = 64, w: int = 128) -> np.ndarray:
    """An outdoor HDR panorama [h, w, 3]: Hosek–Wilkie sky + sun (Mitsuba ``sunsky``, random
    elevation, turbidity, ground albedo), the sun disc added with its exact power, a ground
    and a skyline of random height lit by the sky (Lambert)."""
    elev = np.radians(rng.uniform(2.0, 75.0))
    az = rng.uniform(0, 2 * np.pi)
    sd = np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
    turb = float(rng.uniform(1.5, 8.0))
    alb = rng.uniform(0.08, 0.35) * np.clip(np.array([1.0, 0.9, 0.7]) * rng.uniform(0.85, 1.15, 3), 0, 1)
    sky = mi.load_dict({"type": "sunsky", "sun_direction": sd.tolist(), "turbidity": turb,
                        "albedo": {"type": "rgb", "value": alb.tolist()}, "sun_scale": 0.0})
    sun = mi.load_dict({"type": "sunsky", "sun_direction": sd.tolist(), "turbidity": turb,
                        "sky_scale": 0.0})
    d = equirect_directions(h, w).reshape(-1, 3)
    img = _eval_emitter(sky, d).reshape(h, w, 3)
    half = np.radians(0.5358 / 2)
    sun_power = _eval_emitter(sun, sd[None])[0] * 2 * np.pi * (1 - np.cos(half))   # [3]
    sun_power *= rng.choice([0.0, 1.0], p=[0.15, 0.85])                              # overcast
    sa = solid_angle_image(h, w)
    up = d[:, 2].reshape(h, w)
    e_sky = (img * (sa * np.maximum(up, 0))[..., None]).sum((0, 1))                  # [3]
    e_ground = e_sky + sun_power * max(sd[2], 0.0)                                     # [3]
    # ground + skyline (objects at the horizon: trees/buildings), Lambertian, sky-lit
    tint = rng.uniform(0.8, 1.0, 3)
    tex = _fbm(rng, h, w)[..., None]
    ground = (alb * tint * (0.5 + tex)) * e_ground / np.pi
    prof = _fbm(rng, 3, w, 3)[1] * np.radians(rng.uniform(0, 25))                    # [w]
    elev_px = np.pi / 2 - np.arccos(np.clip(up, -1, 1))                               # [h, w]
    sky_line = elev_px < prof[None]
    obj_col = rng.uniform(0.05, 0.35, 3) * (0.6 + 0.8 * tex)
    facade = obj_col * (0.3 * e_sky + 0.5 * sun_power * rng.uniform(0, 1)) / np.pi
    img = np.where((up < 0)[..., None], ground, np.where(sky_line[..., None], facade, img))
    if sun_power.max() > 0:
        _splat_direction(img, sd, sun_power)
    return img.astype(np.float32)


def interior_colour(rng: np.random.Generator, lo: float, hi: float, warm: float = 0.6) -> np.ndarray:
    """A diffuse albedo [3] as interiors have them: value in [lo, hi], saturation mostly low
    (0–0.6, skewed to 0), hue warm (wood, beige, terracotta) with probability ``warm``, else any:
    a net trained on near-grey rooms fills holes greyer than real interiors."""
    hue = rng.uniform(0.02, 0.14) if rng.random() < warm else rng.uniform(0.0, 1.0)
    sat = 0.6 * rng.beta(1.2, 2.5)
    return np.clip(np.array(colorsys.hsv_to_rgb(hue, sat, rng.uniform(lo, hi))), 0.02, 0.95)


def _room_dict(rng, bulbs: bool = False, finished: bool = False
               ) -> tuple[dict, np.ndarray, np.ndarray]:
    """Mitsuba scene dict of a procedural room, and the box to pick the viewpoint in.
    ``bulbs``: half of the rooms also get 1–4 bare bulbs (see ``room_panorama``).
    ``finished``: a finished interior (``_finish_room``) instead of the plain colours."""
    T = mi.ScalarTransform4f
    sx, sy, sz = rng.uniform(3, 9), rng.uniform(3, 9), rng.uniform(2.3, 4.0)

    def diffuse(c):
        return {"type": "twosided", "bsdf": {"type": "diffuse",
                                             "reflectance": {"type": "rgb", "value": list(c)}}}

    def wall_col():
        return interior_colour(rng, 0.3, 0.85)

    d = {"type": "scene", "integrator": {"type": "path", "max_depth": 5}}
    d["floor"] = {"type": "rectangle", "to_world": T().scale([sx / 2, sy / 2, 1]),
                  "bsdf": diffuse(interior_colour(rng, 0.1, 0.7, warm=0.8))}
    d["ceiling"] = {"type": "rectangle", "to_world": T().translate([0, 0, sz]) @ T().scale(
        [sx / 2, sy / 2, 1]), "bsdf": diffuse(wall_col())}
    walls = [((sx / 2, 0), (0, 1, 0), 90, sy), ((-sx / 2, 0), (0, 1, 0), -90, sy),
             ((0, sy / 2), (1, 0, 0), -90, sx), ((0, -sy / 2), (1, 0, 0), 90, sx)]
    wc = wall_col()
    for i, ((x, y), ax, ang, length) in enumerate(walls):
        tw = T().translate([x, y, sz / 2]) @ T().rotate(ax, ang)
        sc = [sz / 2, length / 2, 1] if ax == (0, 1, 0) else [length / 2, sz / 2, 1]
        d[f"wall{i}"] = {"type": "rectangle", "to_world": tw @ T().scale(sc), "bsdf": diffuse(wc)}
        if rng.random() < 0.45:   # a bright window in this wall, slightly inside it
            ww, wh = rng.uniform(0.6, min(2.5, length * 0.6)), rng.uniform(0.6, sz * 0.6)
            off = rng.uniform(-(length - ww) / 2, (length - ww) / 2)
            zc = rng.uniform(wh / 2 + 0.3, sz - wh / 2 - 0.1)
            inward = -np.sign([x, y, 0][0] or 0) if ax == (0, 1, 0) else -np.sign(y)
            if ax == (0, 1, 0):
                pos = [x + inward * 0.01, off, zc]
                rot = T().rotate([0, 1, 0], 90 * inward)
                scl = [wh / 2, ww / 2, 1]
            else:
                pos = [off, y + inward * 0.01, zc]
                rot = T().rotate([1, 0, 0], -90 * inward)
                scl = [ww / 2, wh / 2, 1]
            col = np.array([0.75, 0.85, 1.0]) * rng.uniform(0.85, 1.15, 3)
            d[f"window{i}"] = {"type": "rectangle", "to_world": T().translate(pos) @ rot @ T().scale(scl),
                               "emitter": {"type": "area", "radiance": {
                                   "type": "rgb", "value": (col * 10 ** rng.uniform(0.3, 1.7)).tolist()}}}
    has_window = any(k.startswith("window") for k in d)
    for i in range(int(rng.integers(0 if has_window else 1, 4))):   # ceiling lamps, facing down
        s = rng.uniform(0.1, 0.6, 2)
        pos = [rng.uniform(-sx / 3, sx / 3), rng.uniform(-sy / 3, sy / 3), sz - 0.01]
        warm = np.array([1.0, rng.uniform(0.75, 0.95), rng.uniform(0.5, 0.85)])
        d[f"lamp{i}"] = {"type": "rectangle", "to_world": T().translate(pos) @ T().rotate(
            [1, 0, 0], 180) @ T().scale([s[0], s[1], 1]), "emitter": {"type": "area", "radiance": {
                "type": "rgb", "value": (warm * 10 ** rng.uniform(1.0, 2.5)).tolist()}}}
    if bulbs and rng.random() < 0.5:       # bare bulbs: pendants below the ceiling, sconces
        for i in range(int(rng.integers(1, 5))):
            r = rng.uniform(0.02, 0.08)
            if rng.random() < 0.5:
                c = [rng.uniform(-sx / 3, sx / 3), rng.uniform(-sy / 3, sy / 3),
                     sz - rng.uniform(0.2, 0.9)]
            else:
                k = int(rng.integers(4))
                along = rng.uniform(-0.4, 0.4) * (sy if k < 2 else sx)
                c = ([(1 if k == 0 else -1) * (sx / 2 - 0.12), along] if k < 2
                     else [along, (1 if k == 2 else -1) * (sy / 2 - 0.12)]) + [rng.uniform(1.5, 2.2)]
            warm = np.array([1.0, rng.uniform(0.7, 0.95), rng.uniform(0.4, 0.85)])
            d[f"bulb{i}"] = {"type": "sphere", "center": [float(v) for v in c], "radius": r,
                             "emitter": {"type": "area", "radiance": {
                                 "type": "rgb", "value": (warm * 10 ** rng.uniform(2.5, 4.5)).tolist()}}}
    for i in range(int(rng.integers(2, 9))):                      # furniture
        x, y = rng.uniform(-sx / 2 + 0.4, sx / 2 - 0.4), rng.uniform(-sy / 2 + 0.4, sy / 2 - 0.4)
        col = rng.uniform(0.05, 0.8, 3)
        if rng.random() < 0.6:
            s = rng.uniform(0.15, 0.8, 3)
            d[f"obj{i}"] = {"type": "cube", "to_world": T().translate([x, y, s[2]]) @ T().rotate(
                [0, 0, 1], rng.uniform(0, 90)) @ T().scale(s.tolist()), "bsdf": diffuse(col)}
        else:
            r = rng.uniform(0.1, 0.5)
            d[f"obj{i}"] = {"type": "sphere", "center": [x, y, r], "radius": r, "bsdf": diffuse(col)}
    if finished:
        _finish_room(rng, d, sx, sy, sz, diffuse)
    lo = np.array([-sx / 4, -sy / 4, 0.8])
    hi = np.array([sx / 4, sy / 4, min(1.8, sz - 0.5)])
    return d, lo, hi


def _finish_room(rng, d: dict, sx: float, sy: float, sz: float, diffuse) -> None:
    """Repaint and relight room dict ``d`` in place as a finished interior: a white or pale
    ceiling and pale walls over a saturated wood floor (70 %), 2–8 strip lights in rows on the
    ceiling (cool or neutral white), and with probability ½ 2–4 uplights near the walls that
    make the ceiling the brightest surface. Why: the plain rooms have ceilings no brighter
    or bluer than their floors, so the scene-label classifier learnt "bright, bluer top" as
    outdoor, and read a real hall with a white ceiling over a wooden floor as outdoor."""
    T = mi.ScalarTransform4f
    pale = lambda lo, hi, smax: np.clip(np.array(colorsys.hsv_to_rgb(       # noqa: E731
        rng.uniform(0.0, 1.0), rng.uniform(0.0, smax), rng.uniform(lo, hi))), 0.02, 0.95)
    d["ceiling"]["bsdf"] = diffuse(pale(0.7, 0.95, 0.06))
    wall = pale(0.55, 0.9, 0.15)
    for k in [k for k in d if k.startswith("wall")]:
        d[k]["bsdf"] = diffuse(wall)
    if rng.random() < 0.7:              # wood: orange-brown, saturated
        wood = colorsys.hsv_to_rgb(rng.uniform(0.04, 0.11), rng.uniform(0.45, 0.8),
                                   rng.uniform(0.2, 0.6))
        d["floor"]["bsdf"] = diffuse(np.clip(np.array(wood), 0.02, 0.95))
    n, along_x = int(rng.integers(2, 9)), bool(rng.random() < 0.5)
    cool = np.array([rng.uniform(0.9, 1.0), rng.uniform(0.95, 1.0), 1.0])
    length, span = (sx, sy) if along_x else (sy, sx)
    for i in range(n):                  # strip lights, facing down
        hl = rng.uniform(0.3, min(0.7, 0.3 * length))
        a = rng.uniform(-length / 2 + hl + 0.1, length / 2 - hl - 0.1)
        b = (i + 0.5) / n * span - span / 2
        pos = [a, b, sz - 0.01] if along_x else [b, a, sz - 0.01]
        scl = [hl, 0.04, 1] if along_x else [0.04, hl, 1]
        d[f"strip{i}"] = {"type": "rectangle", "to_world": T().translate(pos) @ T().rotate(
            [1, 0, 0], 180) @ T().scale(scl), "emitter": {"type": "area", "radiance": {
                "type": "rgb", "value": (cool * 10 ** rng.uniform(1.5, 2.7)).tolist()}}}
    if rng.random() < 0.5:
        for i in range(int(rng.integers(2, 5))):      # uplights on the walls, facing up
            k = int(rng.integers(4))
            s = rng.uniform(0.1, 0.3)
            along = rng.uniform(-0.35, 0.35) * (sy if k < 2 else sx)
            xy = ([(1 if k == 0 else -1) * (sx / 2 - s - 0.05), along] if k < 2
                  else [along, (1 if k == 2 else -1) * (sy / 2 - s - 0.05)])
            warm = np.array([1.0, rng.uniform(0.8, 0.95), rng.uniform(0.6, 0.85)])
            d[f"uplight{i}"] = {"type": "rectangle", "to_world": T().translate(
                [*xy, sz - rng.uniform(0.5, 1.0)]) @ T().scale([s, s, 1]),
                "emitter": {"type": "area", "radiance": {
                    "type": "rgb", "value": (warm * 10 ** rng.uniform(1.5, 2.5)).tolist()}}}


def room_panorama(rng: np.random.Generator, h: int = 64, w: int = 128, spp: int = 32,
                  seed: int = 0, bulbs: bool = False, finished: bool = False) -> np.ndarray:
    """An indoor HDR panorama [h, w, 3] path traced (Mitsuba ``path``, 5 bounces) from a point
    in a procedural room (random size and wall colours, 0–4 windows, 0–3 ceiling lamps, boxes
    and balls). Each pixel averages ``spp`` stratified-jittered rays over its footprint.
    ``bulbs``: half of the rooms also get 1–4 bare bulbs (spheres of 2–8 cm radius below the
    ceiling or on the walls, radiance 10^2.5–10^4.5, 10–100× the panels'): the real interiors'
    small lamps are 100–250× their clipped EV-0 power, the panels only up to ~30×.
    ``finished``: a white ceiling, pale walls, a wood floor, strip lights and uplights
    (``_finish_room``)."""

    d, lo, hi = _room_dict(rng, bulbs, finished)
    scene = mi.load_dict(d)
    s = max(1, int(round(np.sqrt(spp))))
    dirs = pixel_directions(w, h, 0, w * h, s, rng).astype(np.float32)        # [h*w*s*s, 3]
    o = rng.uniform(lo, hi)
    n = len(dirs)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    ray = mi.Ray3f(mi.Point3f(*[dr.full(mi.Float, float(c), n) for c in o]),
                   to_jit(mi.Vector3f, dirs.T))
    with dr.suspend_grad():
        L, _, _ = scene.integrator().sample(scene, sampler, ray)
        L = np.asarray(L, np.float64).T.reshape(h * w, s * s, 3).mean(1)
    return np.nan_to_num(L.reshape(h, w, 3), nan=0.0, posinf=0.0).clip(0).astype(np.float32)
