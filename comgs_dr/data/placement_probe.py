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
estimate of the package). Each pixel averages ``spp_side``² stratified jittered directions in
(u, v): a sun smaller than a pixel is then integrated with its share of the pixel's area
(uniform in (u, v), which is within cos-of-half-a-pixel of uniform in solid angle), not hit
or missed by a few random rays.

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

from comgs_dr.core.equirect import equirect_uv_to_dir_np
from comgs_dr.data import composition_dataset as comp
from comgs_dr.lighting.envmap import load_envmap, write_exr

__all__ = ["render_probe", "empty_scene", "placement_position", "placement_probe",
           "write_probes"]


def render_probe(scene: "mi.Scene", position, height: int = 128, spp_side: int = 8,
                 seed: int = 0, progress=None) -> np.ndarray:
    """[height, 2·height, 3] float32 radiance arriving at ``position`` [3] (world) from every
    equirect direction, with the scene's integrator; ``spp_side``² stratified samples per
    pixel. ``progress``: optional callable(done, total) after each pass."""
    h, k = int(height), int(spp_side)
    if h < 1 or k < 1:
        raise ValueError(f"render_probe: height and spp_side must be >= 1, got {height}, {spp_side}")
    p = np.asarray(position, np.float64).reshape(-1)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"render_probe: position must be 3 finite numbers, got {position!r}")
    integ = scene.integrator()
    if not isinstance(integ, mi.SamplingIntegrator):
        raise ValueError(f"render_probe: the scene's integrator must be a sampling integrator "
                         f"(path, direct, ...), got {type(integ).__name__}")
    w = 2 * h
    n = h * w
    # every stratum of every pixel, stratum-major: [k², N] ray batches in chunks of <= 2^21
    sy, sx = np.divmod(np.arange(k * k), k)                                     # [k²]
    ys, xs = np.divmod(np.arange(n), w)                                         # [N]
    rng = np.random.default_rng(seed)
    sampler = mi.load_dict({"type": "independent"})
    acc = np.zeros((n, 3))
    per = max(1, (1 << 21) // n)                                  # strata per launch
    for c0 in range(0, k * k, per):
        st = slice(c0, min(k * k, c0 + per))
        m = len(sx[st]) * n
        jit = rng.random((2, m))
        u = (np.tile(xs, len(sx[st])) + (np.repeat(sx[st], n) + jit[0]) / k) / w
        v = (np.tile(ys, len(sy[st])) + (np.repeat(sy[st], n) + jit[1]) / k) / h
        d = equirect_uv_to_dir_np(np.stack([u, v], -1)).astype(np.float32)    # [M, 3]
        ray = mi.Ray3f(mi.Point3f(*[np.full(m, c, np.float32) for c in p]),
                       mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        sampler.seed(seed * 1_000_003 + c0, m)
        spec, _, _ = integ.sample(scene, sampler, ray)
        rgb = mi.Color3f(spec)
        dr.eval(rgb)
        vals = np.stack([np.asarray(rgb[c], np.float64) for c in range(3)], -1)   # [M, 3]
        acc += vals.reshape(-1, n, 3).sum(0)
        if progress is not None:
            progress(st.stop, k * k)
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


def placement_position(ds_dir, name: str | None = None) -> np.ndarray:
    """[3] world position of object ``name``'s placement (the first object if None): the
    translation of its ``transform.json`` entry, where ``estimate-light`` is run."""
    tr = json.loads((Path(ds_dir) / "transform.json").read_text())
    if name is None:
        name = next(iter(tr))
    if name not in tr:
        raise KeyError(f"{ds_dir}: no placement {name!r} (has {', '.join(tr)})")
    return np.asarray(tr[name]["transform"], np.float64).reshape(4, 4)[:3, 3]


def placement_probe(ds_dir, name: str | None = None, height: int = 128,
                    spp_side: int = 8, seed: int = 0) -> np.ndarray:
    """[height, 2·height, 3] true light at object ``name``'s placement in the empty scene."""
    return render_probe(empty_scene(ds_dir), placement_position(ds_dir, name), height,
                        spp_side, seed)


def write_probes(ds_dir, height: int = 128, spp_side: int = 8, seed: int = 0) -> dict:
    """``probes/<name>.exr`` (linear RGB equirect, layout metadata) of the true light at every
    object's placement in the composition dataset ``ds_dir``; returns {name: path}."""
    ds = Path(ds_dir)
    scene = empty_scene(ds)
    names = json.loads((ds / "transform.json").read_text())
    out = {}
    for name in names:
        img = render_probe(scene, placement_position(ds, name), height, spp_side, seed)
        out[name] = write_exr(ds / "probes" / f"{name}.exr", img, "equirect")
    return out
