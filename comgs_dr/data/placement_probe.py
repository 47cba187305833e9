"""The true light at a placement: an HDR equirect probe path-traced in a composition scene.

Lighting estimation at a placement (``comgs estimate-light``) is meant to recover the light
that *arrives there*: the sky where the scene leaves it open, the lit ground and walls
below and around it, nothing where the scene's own shapes hide the sun. The scene's map
itself is not that light (its lower half is a different ground, and it ignores what the
scene occludes and reflects), so ``benchmarks/recon_light_e2e.py`` scores estimates against
this probe: the composition dataset's scene *without* the objects, path-traced (its own
``path`` integrator, max depth and map scale) along every equirect direction from the
placement.

Direction of pixel (x, y) of an [H, 2H] probe: ``core.equirect.equirect_uv_to_dir_np`` of
(u, v) = ((x + ½)/W, (y + ½)/H) (Blender's Z-up equirect, the frame of every map, trace and
estimate of the package). Each pixel averages ``spp_side``² stratified jittered directions,
each stratum an equal solid angle of the pixel (uniform in u and cos θ): a sun smaller than
a pixel is integrated with its share of the pixel's solid angle, not hit or missed by a few
random rays, and not over-weighted near a pole (jitter uniform in θ gave a one-texel sun
at 1° from the zenith 4.2× its power in a 16-row probe).

Hand-written: Mitsuba 3 has no spherical camera among its sensors; the rays are built here and
given to the scene's integrator (``SamplingIntegrator.sample``), as a sensor would.
"""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.equirect import pixel_directions
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.similarity import read_placements
from comgs_dr.data import composition_dataset as comp
from comgs_dr.lighting.envmap import load_envmap, write_exr

MAX_HEIGHT = 4096          # rows (a float64 accumulator of 4096 x 8192 x 3 is 0.8 GB)

__all__ = ["render_probe", "empty_scene", "placement_position", "placement_probe",
           "write_probes"]


def render_probe(scene: "mi.Scene", position, height: int = 128, spp_side: int = 8,
                 seed: int = 0, progress=None, world_from_probe=None) -> np.ndarray:
    """[height, 2·height, 3] float32 radiance arriving at ``position`` [3] (world) from every
    equirect direction, with the scene's integrator; ``spp_side``² stratified samples per
    pixel, equal in solid angle (``core.equirect.pixel_directions(equal_area=True)``; one:
    the pixel centre). Rays go in launches of at most 2²¹. ``progress``: optional
    callable(pixels done, pixels) after each launch. ``world_from_probe`` [3, 3]: a rotation
    taking the probe's pixel directions into the scene's world (the probe in another frame,
    e.g. a reconstruction's); None: the world's own."""
    h, k = int(height), int(spp_side)
    if not (1 <= h <= MAX_HEIGHT and k >= 1):
        raise ValueError(f"render_probe: height must be in [1, {MAX_HEIGHT}] and spp_side "
                         f">= 1, got {height}, {spp_side}")
    p = np.asarray(position, np.float64).reshape(-1)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"render_probe: position must be 3 finite numbers, got {position!r}")
    R = np.eye(3) if world_from_probe is None else np.asarray(world_from_probe, np.float64)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) \
            or np.linalg.det(R) < 0:
        raise ValueError(f"render_probe: world_from_probe must be a 3×3 rotation, got "
                         f"{np.asarray(world_from_probe).tolist()!r:.120}")
    integ = scene.integrator()
    if not isinstance(integ, mi.SamplingIntegrator):
        raise ValueError(f"render_probe: the scene's integrator must be a sampling integrator "
                         f"(path, direct, ...), got {type(integ).__name__}")
    w = 2 * h
    n = h * w
    rng = np.random.default_rng(seed)
    sampler = mi.load_dict({"type": "independent"})
    acc = np.zeros((n, 3))
    step = max(1, (1 << 21) // (k * k))                           # pixels per launch
    for p0 in range(0, n, step):
        p1 = min(n, p0 + step)
        m = (p1 - p0) * k * k
        d = (pixel_directions(w, h, p0, p1, k, rng, equal_area=True) @ R.T).astype(np.float32)
        origin = mi.Point3f(*[dr.full(mi.Float, float(c), m) for c in p])
        ray = mi.Ray3f(origin, to_jit(mi.Vector3f, d.T))
        sampler.seed(seed * 1_000_003 + p0, m)
        spec, _, _ = integ.sample(scene, sampler, ray)
        rgb = mi.Color3f(spec)
        dr.eval(rgb)
        vals = np.stack([np.asarray(rgb[c], np.float64) for c in range(3)], -1)   # [M, 3]
        acc[p0:p1] = vals.reshape(p1 - p0, k * k, 3).sum(1)
        if progress is not None:
            progress(p1, n)
    out = (acc / (k * k)).reshape(h, w, 3)
    if not np.isfinite(out).all():
        raise ValueError("render_probe: the integrator returned non-finite radiance")
    return out.astype(np.float32)


def _meta(ds_dir) -> dict:
    f = Path(ds_dir) / "composition.json"
    if not f.is_file():
        raise FileNotFoundError(f"{ds_dir}: no composition.json (not a composition dataset)")
    return json.loads(f.read_text())


def empty_scene(ds_dir) -> "mi.Scene":
    """The composition dataset's scene without the objects, rebuilt from its
    ``composition.json`` (shapes, textures, map, map scale, integrator depth)."""
    ds = Path(ds_dir)
    meta = _meta(ds)
    sc = meta["scene"]
    layout, textures = {}, {}
    for key, sh in sc["shapes"].items():
        sh = dict(sh)
        sh["to_world"] = np.asarray(sh["to_world"], np.float64)
        if sh.get("texture"):
            textures[Path(sh["texture"]).stem] = ds / sh["texture"]
            sh["texture"] = Path(sh["texture"]).stem
        layout[key] = sh
    cfg = SimpleNamespace(max_depth=meta["render"]["max_depth"],
                          scene_envmap_scale=sc["envmap_scale"],
                          fov_deg=meta["render"]["fov_deg"], resolution=8)
    return mi.load_dict(comp.scene_dict(cfg, load_envmap(sc["envmap"]), textures, layout))


def placement_position(ds_dir, name: str | None = None, at: str = "origin") -> np.ndarray:
    """[3] world position at object ``name``'s placement (the first object if None): ``at``
    "origin", the translation of its ``transform.json`` entry (the placed object frame's
    origin), or "centre", the centre of its world bounding box (``composition.json``), where
    ``compose`` estimates the lighting (at the reconstructed object's box centre)."""
    if at not in ("origin", "centre"):
        raise ValueError(f"placement_position: at must be 'origin' or 'centre', got {at!r}")
    tr = read_placements(Path(ds_dir) / "transform.json")
    name = next(iter(tr)) if name is None else name
    if name not in tr:
        raise KeyError(f"{ds_dir}: no placement {name!r} (has {', '.join(tr)})")
    if at == "origin":
        return np.asarray(tr[name].translation, np.float64)
    lo, hi = np.asarray(_meta(ds_dir)["objects"][name]["bbox_world"], np.float64)
    return (lo + hi) / 2


def placement_probe(ds_dir, name: str | None = None, height: int = 128, spp_side: int = 8,
                    seed: int = 0, at: str = "origin") -> np.ndarray:
    """[height, 2·height, 3] true light at object ``name``'s placement (``placement_position``)
    in the empty scene."""
    return render_probe(empty_scene(ds_dir), placement_position(ds_dir, name, at), height,
                        spp_side, seed)


def write_probes(ds_dir, height: int = 128, spp_side: int = 8, seed: int = 0) -> dict:
    """``probes/<name>.exr`` (linear RGB equirect, layout metadata) of the true light at the
    centre of every object's box in the composition dataset ``ds_dir`` (where ``compose``
    estimates it), and ``probes/probes.json`` with those positions; returns {name: path}."""
    ds = Path(ds_dir)
    scene = empty_scene(ds)
    out, where = {}, {}
    for name in read_placements(ds / "transform.json"):
        pos = placement_position(ds, name, "centre")
        out[name] = write_exr(ds / "probes" / f"{name}.exr",
                              render_probe(scene, pos, height, spp_side, seed), "equirect")
        where[name] = {"position": pos.tolist(), "at": "centre of the object's world box",
                       "height": int(height), "strata_per_pixel": int(spp_side) ** 2}
    (ds / "probes" / "probes.json").write_text(json.dumps(where, indent=1))
    return out
