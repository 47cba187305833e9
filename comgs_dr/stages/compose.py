"""``comgs compose``: the edit stage of a composition (paper, "Occlusion Caching").

Inputs: a step-1 scene run, one step-2 object run per object, placements
(``transform.json``) and the lighting (one equirect/octahedral map for every object, or an
``estimator(position, name) -> equirect radiance`` run at each object's centre, e.g.
``stages.estimate_light.PlacementEstimator``). Output, in ``COMP_DIR``:

* ``env/<name>.exr`` — octahedral map lighting each object (``comgs compose`` without
  ``--env`` also keeps each estimate's own files, as ``comgs estimate-light`` writes them, in
  ``env/<name>_estimate/``: ``<name>.json``, the preview, the equirect map);
* ``probes/<name>.npz`` — the object's own SOPs placed in the world
  (:func:`~comgs_dr.sops.occlusion.transform_probes`), occlusion by the other objects added;
* ``shadow_probes.npz`` — shadow-region probes on the scene around every object with the
  occlusion of *all* objects (1 − Π_j (1 − O_j)), so each shadow is right with several
  objects, including objects that shadow each other;
* ``cache/`` — per (receiver probe set, occluder) occlusion textures, keyed by what they
  depend on (files, placements, settings): moving or replacing one object re-traces only
  the pairs it is part of;
* ``composition.json`` (manifest, see ``data.comp_folder``), ``composition.xml``,
  ``edit.json`` (timings of lighting, probe placement and occlusion tracing; pair counts);
  both record each object's exposure gain (``data.exposure``: the gain, how it was found,
  what was assumed);
* ``objects/<name>.ply`` — the object's surfels with its albedo × its exposure gain, where
  that gain is not 1 (the manifest then names this file).

:func:`compose` runs the phases in order: check the inputs, load and place the objects,
light them (:func:`_lighting`), place the probes (:func:`_place_probes`), trace the
occlusion pairs (:func:`_trace_occlusion`), write the probe files and the manifest.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import mitsuba as mi
import numpy as np
from tqdm.auto import tqdm

from comgs_dr.data import comp_folder
from comgs_dr.data import exposure as xp
from comgs_dr.surfels.params import object_bounds
from comgs_dr.lighting import envmap as em
from comgs_dr.sops import occlusion as occ
from comgs_dr.sops.placement import PlacementConfig, fuse_depth, render_geometry
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.surfels.io import load_ply, save_ply
from comgs_dr.surfels.shape import SurfelShapeBase
from comgs_dr.surfels.transform import transform_surfels
from comgs_dr.core import runlog
from comgs_dr.core.similarity import read_placements
from comgs_dr.train.run import load_run_dataset, read_run_info, select_views
from comgs_dr.train.checkpoint import atomic_write_text

log = logging.getLogger(__name__)


@dataclass
class ComposeConfig:
    """Settings of :func:`compose` (paper sec. 4.1: 10k shadow probes per object, a region
    6× the object's bounds; here 32² texels a probe).

    shadow: the shadow-region probes (``sops.occlusion.ShadowConfig``: count per object,
        texels a side, region size, ...).
    env_res: octahedral texels per side of each object's light map (default 256).
    scene_views: scene views rendered to find the scene's surface points (default 16).
    min_consistent: other views that must agree on a surface point (default 2).
    max_hits: surfels composited per occlusion ray (default 32).
    seed: seed of the shadow-region probe placement; object i uses seed + i (default 0).
    """
    shadow: occ.ShadowConfig = field(default_factory=occ.ShadowConfig)
    env_res: int = 256
    scene_views: int = 16
    min_consistent: int = 2
    max_hits: int = 32
    seed: int = 0


PRESETS = {"default": ComposeConfig(),
           "fast": ComposeConfig(shadow=occ.ShadowConfig(count=2000, res=16),
                                 scene_views=8)}


def compose_config(preset: str = "default", shadow_probes: int | None = None,
                   **fields) -> ComposeConfig:
    """The preset's :class:`ComposeConfig` with ``fields`` (its scalar fields, e.g.
    ``scene_views=8``) and ``shadow_probes`` (``shadow.count``, ≥ 1) replaced.

    >>> compose_config("fast", shadow_probes=500).shadow.count
    500
    """
    if preset not in PRESETS:
        raise ValueError(f"compose: preset must be one of {sorted(PRESETS)}, got {preset!r}")
    cfg = dataclasses.replace(PRESETS[preset], **fields) if fields else PRESETS[preset]
    if shadow_probes is not None:
        if shadow_probes < 1:
            raise ValueError(f"--shadow-probes must be ≥ 1, got {shadow_probes}")
        cfg = dataclasses.replace(cfg, shadow=dataclasses.replace(cfg.shadow,
                                                                  count=shadow_probes))
    return cfg


def object_files(run) -> dict:
    """{'ply', 'probes', 'dir'} of a step-2 run: ``RUN`` itself or ``RUN/material``."""
    run = Path(run)
    for d in (run, run / "material"):
        if (d / "point_cloud.ply").is_file() and (d / "probes.npz").is_file():
            return {"ply": d / "point_cloud.ply", "probes": d / "probes.npz", "dir": d}
    raise FileNotFoundError(f"{run}: no step-2 output (point_cloud.ply + probes.npz in it or "
                            f"in {run / 'material'}); run `comgs decompose` on the object first")


def _stat(p: Path) -> list:
    s = Path(p).stat()
    return [str(Path(p).resolve()), s.st_size, s.st_mtime_ns]


def _key(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


class _Cache:
    """Arrays in ``COMP_DIR/cache/<name>.npz`` stored with the key they were made from."""

    def __init__(self, root: Path):
        self.root = root / "cache"
        self.root.mkdir(parents=True, exist_ok=True)
        self.hits, self.misses = [], []

    def get(self, name: str, key: str, make):
        p = self.root / f"{name}.npz"
        if p.is_file():
            with np.load(p, allow_pickle=False) as z:
                if str(z["key"]) == key:
                    self.hits.append(name)
                    return {k: z[k] for k in z.files if k != "key"}
        out = make()
        tmp = p.with_name(p.name + ".tmp.npz")
        np.savez_compressed(tmp, key=np.array(key), **out)
        tmp.replace(p)
        self.misses.append(name)
        return out


def compose(scene_run, objects: dict, placement, out, env=None, estimator=None,
            cfg: ComposeConfig = ComposeConfig(), progress: bool = True,
            exposure=None) -> dict:
    """Build (or update) a composition folder; returns the ``edit.json`` summary.

    ``objects``: {name: step-2 run folder}; ``placement``: a ``transform.json`` path or
    {name: Similarity}; ``env``: one map for all objects (equirect Z-up or octahedral
    EXR) — or ``estimator``: callable(world position [3], object name) -> equirect
    radiance [H, W, 3] (the name lets it keep its own record of each estimate).
    ``exposure``: the object → scene gain on each object's albedo (``data.exposure``): an
    ``ExposureGain`` for every object, {name: ExposureGain}, ``"grey-world"`` (each from
    its own albedo) or None (gain 1, assumed, and said so in composition.json).
    A folder this call created is removed again when it fails before writing a file.
    """
    out = Path(out)
    created = not out.exists()
    try:
        return _compose(scene_run, objects, placement, out, env, estimator, cfg, progress,
                        exposure)
    except BaseException:
        if created and out.is_dir():
            _remove_empty_folders(out)
        raise


def _remove_empty_folders(out: Path) -> None:
    """``out`` and its sub-folders, where they hold no file (a failed first run)."""
    try:
        for d in sorted(out.rglob("*"), reverse=True):   # empty sub-folders first
            if d.is_dir() and not any(d.iterdir()):
                d.rmdir()
        if not any(out.iterdir()):
            out.rmdir()
    except OSError:                 # the original error matters, not the cleanup's
        pass


MIN_RELATIVE_SIZE = 1e-4    # a placed object smaller than this × the scene: a wrong scale


def _compose(scene_run, objects, placement, out: Path, env, estimator, cfg, progress,
             exposure=None) -> dict:
    t_all = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    timings = {}
    inputs = _check_inputs(Path(scene_run), objects, placement)
    t = time.perf_counter()
    world = _place_objects(inputs, objects)
    timings["load"] = time.perf_counter() - t

    light = _lighting(list(objects), world.centres, env, estimator, cfg.env_res, out, timings)

    cache = _Cache(out)
    t = time.perf_counter()
    regions, own = _place_probes(cache, world, cfg)
    timings["probe_placement"] = time.perf_counter() - t

    t = time.perf_counter()
    textures, culled = _trace_occlusion(cache, world, regions, own, cfg, progress)
    timings["occlusion_tracing"] = time.perf_counter() - t

    t = time.perf_counter()                  # what the renderer reads
    shadow = _write_probes(out, world.names, regions, own, textures, cfg.shadow.res)
    gains = _apply_exposure(out, world, exposure)
    _write_manifest(out, world, objects, light["source"], cfg, gains)
    timings["write"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    summary = _summary(timings, shadow, regions, own, cache, culled, cfg)
    summary["exposure"] = {n: g for n, (g, _) in gains.items()}
    atomic_write_text(out / "edit.json", json.dumps(runlog.json_safe(summary), indent=1,
                                                     allow_nan=False))
    runlog.rewrite(out, runlog.part_records("compose", timings, shadow_probes=shadow.count))
    return summary


# ---------------------------------------------------------------------------------------
# Phase 1: inputs, and the objects placed in the scene's world frame

@dataclass
class _Inputs:
    """The checked inputs of :func:`compose`."""
    scene_run: Path
    info: dict                 # the scene run's run.json
    scene_ply: Path
    placements: dict           # {name: Similarity}, in the scene dataset's frame
    files: dict                # {name: object_files(run)}


@dataclass
class _World:
    """The scene and the objects in the world frame: what every later phase reads."""
    inputs: _Inputs
    names: list                # the objects, in the order given
    train_views: list          # the scene dataset's training views (cameras only)
    W: np.ndarray              # world_from_source [4, 4]
    scene_params: object       # the scene's surfels
    scene_meta: object         # its PLY metadata (colour space)
    sims: dict                 # {name: Similarity}, object to world
    surfels: dict              # {name: the object's surfels placed in the world}
    bounds: dict               # {name: (lo [3], hi [3])} of the placed surfels

    @property
    def centres(self) -> dict:
        return {n: (self.bounds[n][0] + self.bounds[n][1]) / 2 for n in self.names}


def _check_inputs(scene_run: Path, objects: dict, placement) -> _Inputs:
    """The scene run, the placements and each object's files; errors name what is wrong."""
    info = read_run_info(scene_run)
    scene_ply = scene_run / "point_cloud.ply"
    if not scene_ply.is_file():
        raise FileNotFoundError(f"{scene_ply} not found: finish step 1 on the scene first")
    if not objects:
        raise ValueError("compose: no object given")
    placements = read_placements(placement) if not isinstance(placement, dict) else placement
    missing = [n for n in objects if n not in placements]
    if missing:
        raise ValueError(f"compose: no placement for {missing} in {placement} "
                         f"(placements: {sorted(placements)})")
    extra = [n for n in placements if n not in objects]
    if extra:
        log.warning("compose: placements without an object are ignored: %s", extra)
    bad = [n for n in objects if not n.replace("_", "").replace("-", "").isalnum()]
    if bad:
        raise ValueError(f"compose: object names must be letters, digits, '-' or '_': {bad}")
    files = {n: object_files(r) for n, r in objects.items()}
    return _Inputs(scene_run, info, scene_ply, placements, files)


def _place_objects(inputs: _Inputs, objects: dict) -> _World:
    """Load the scene and the objects; each placement taken to the world frame."""
    data = load_run_dataset(inputs.scene_run, inputs.info, pixels=False)     # cameras only
    W = np.asarray(data.world_from_source, np.float64)
    scene_params, scene_meta = load_ply(str(inputs.scene_ply), return_meta=True)
    sims, placed, bounds = {}, {}, {}
    for n in objects:
        s0 = inputs.placements[n]
        sims[n] = type(s0)(s0.scale, W[:3, :3] @ s0.rotation, W[:3, :3] @ s0.translation + W[:3, 3])
        placed[n] = transform_surfels(load_ply(str(inputs.files[n]["ply"])), sims[n])
        bounds[n] = object_bounds(placed[n])
    world = _World(inputs, list(objects), data.train, W, scene_params, scene_meta, sims,
                   placed, bounds)
    _check_sizes(world)
    return world


def _check_sizes(world: _World) -> None:
    """ValueError for an object placed at a tiny fraction of the scene's size (a wrong
    scale in its placement)."""
    scene_size = float(np.linalg.norm(np.subtract(*object_bounds(world.scene_params)[::-1])))
    for n in world.names:
        lo, hi = world.bounds[n]
        size = float(np.linalg.norm(hi - lo))
        if not size > MIN_RELATIVE_SIZE * scene_size:
            raise ValueError(f"compose: object {n!r} placed at scale {world.sims[n].scale:.3g} "
                             f"is {size:.3g} units across, {size / scene_size:.1e} of the "
                             f"scene's {scene_size:.3g}: check its placement's scale")


# ---------------------------------------------------------------------------------------
# Phase 2: the light of each object

def _lighting(names, centres, env, estimator, res, out: Path, timings: dict) -> dict:
    """Write ``env/<name>.exr`` (octahedral, ``res`` texels a side) for every object: the
    map ``env`` for all, or ``estimator`` at each object's centre. Returns
    {"paths": {name: path}, "source": the manifest's record of where the light came from}."""
    t = time.perf_counter()
    paths = {}
    if env is not None:
        img, layout = em.read_envmap_file(env)
        if not (img > 0).any():
            log.warning("compose: the environment map %s is black: the objects get no light "
                        "from it, only the indirect light baked into their probes at "
                        "reconstruction (not relit), and cast no shadow", env)
        oct_map = img if layout == "octahedral" else em.equirect_to_oct_np(img, res)
        for n in names:
            paths[n] = em.write_exr(out / "env" / f"{n}.exr", oct_map, "octahedral")
        source = {"file": str(Path(env).resolve()), "layout": layout}
    elif estimator is not None:
        for n in names:
            rad = np.asarray(estimator(np.asarray(centres[n]), n), np.float64)  # [H, W, 3]
            paths[n] = em.write_exr(out / "env" / f"{n}.exr",
                                    em.equirect_to_oct_np(rad, res), "octahedral")
        source = {"estimated_at": {n: np.asarray(centres[n]).tolist() for n in names}}
    else:
        raise ValueError("compose: give an environment map (env) or a lighting estimator")
    timings["lighting"] = time.perf_counter() - t
    return {"paths": paths, "source": source}


# ---------------------------------------------------------------------------------------
# Phase 3: probes (each cached under a key of what it depends on)

def _place_probes(cache: _Cache, world: _World, cfg: ComposeConfig) -> tuple[dict, dict]:
    """({name: (shadow-region ProbeSet, key)}, {name: (the object's own ProbeSet, key)})."""
    scene_key = _key(_stat(world.inputs.scene_ply), world.W.tolist(), cfg.scene_views,
                     cfg.min_consistent)
    views = select_views(world.train_views, cfg.scene_views)
    surf = cache.get("scene_surface", scene_key,
                     partial(_scene_surface, world.scene_params, views, cfg.min_consistent))
    regions = {}
    for i, n in enumerate(world.names):
        rkey = _key(scene_key, np.round(world.bounds[n], 6).tolist(), asdict(cfg.shadow),
                    cfg.seed)
        r = cache.get(f"region_{n}", rkey,
                      partial(_region_probes, surf, world.bounds[n], cfg, cfg.seed + i, n))
        regions[n] = (ProbeSet(r["positions"], r["normals"], cfg.shadow.res, float(r["radius"])),
                      rkey)
    own = {}
    for n in world.names:
        files, sim = world.inputs.files[n], world.sims[n]
        okey = _key(_stat(files["probes"]), sim.matrix.round(9).tolist())
        o = cache.get(f"own_{n}", okey, partial(_own_probes, files["probes"], sim))
        own[n] = (ProbeSet(o["positions"], o["normals"], int(o["res"]), float(o["radius"]),
                           texture=o["texture"]), okey)
    return regions, own


def _scene_surface(scene_params, views, min_consistent: int) -> dict:
    """The scene's surface points and normals, fused from the depth of ``views``."""
    pc = PlacementConfig(min_consistent=min_consistent, max_views=len(views))
    bufs = render_geometry(scene_params, [v.camera for v in views])
    fused = fuse_depth([v.camera for v in views], bufs, pc)
    return {"points": fused.points.astype(np.float32), "normals": fused.normals.astype(np.float32)}


def _region_probes(surf: dict, bounds, cfg: ComposeConfig, seed: int, name: str) -> dict:
    """Shadow-region probes on the scene's surface around the object of ``bounds``."""
    ps = occ.shadow_region_probes(surf["points"], surf["normals"], *bounds, cfg.shadow,
                                  seed, name)
    return {"positions": ps.positions, "normals": ps.normals, "radius": np.float64(ps.radius)}


def _own_probes(path: Path, sim) -> dict:
    """The object's step-2 probes taken to the world by ``sim``."""
    ps = occ.transform_probes(ProbeSet.load(path), sim)
    return {"positions": ps.positions, "normals": ps.normals, "texture": ps.texture,
            "radius": np.float64(ps.radius), "res": np.int64(ps.res)}


# ---------------------------------------------------------------------------------------
# Phase 4: occlusion of every receiver probe set by every (other) object, cached per pair

class _Occluders:
    """Each object alone in a Mitsuba scene, loaded the first time it is traced against."""

    def __init__(self, surfels: dict):
        self.surfels, self.scenes = surfels, {}

    def scene(self, name: str):
        if name not in self.scenes:
            self.scenes[name] = mi.load_dict(
                {"type": "scene", name: SurfelShapeBase.from_params(self.surfels[name], id=name)})
        return self.scenes[name]


def _trace_occlusion(cache: _Cache, world: _World, regions: dict, own: dict,
                     cfg: ComposeConfig, progress: bool) -> tuple[dict, list]:
    """({(kind, receiver, occluder): occlusion [P, R, R]}, names of the culled pairs).
    kind "region": the shadow probes around ``receiver``, by every object; "own": the
    receiver's own probes, by every other object."""
    names = world.names
    occluder_keys = {n: _key(_stat(world.inputs.files[n]["ply"]),
                             world.sims[n].matrix.round(9).tolist(), cfg.max_hits,
                             cfg.shadow.supersample) for n in names}
    occluders = _Occluders(world.surfels)
    pairs = [("region", r, j) for r in names for j in names] + \
            [("own", r, j) for r in names for j in names if j != r]
    culled, textures = [], {}
    bar = tqdm(pairs, desc="occlusion", unit="pair", disable=not progress)
    for kind, r, j in bar:
        probes, rkey = (regions if kind == "region" else own)[r]
        name = f"occ_{kind}_{r}__{j}"
        make = partial(_pair_occlusion, probes, world.bounds[j], partial(occluders.scene, j),
                       cfg, name, culled)
        textures[(kind, r, j)] = cache.get(name, _key(rkey, occluder_keys[j]), make)["occlusion"]
    bar.close()
    return textures, culled


def _pair_occlusion(probes: ProbeSet, bounds, occluder_scene, cfg: ComposeConfig, name: str,
                    culled: list) -> dict:
    """The occlusion of ``probes`` by the object of ``bounds`` (traced in
    ``occluder_scene()``), or zero without tracing where the object's bounding sphere
    cannot reach them (``name`` then appended to ``culled``)."""
    lo, hi = bounds
    sphere_r = float(np.linalg.norm(hi - lo)) / 2
    if not occ.can_occlude(probes, (lo + hi) / 2, sphere_r):
        culled.append(name)
        return {"occlusion": np.zeros((probes.count, probes.res, probes.res), np.float32)}
    return {"occlusion": occ.trace_occlusion(probes, occluder_scene(), cfg.shadow.supersample,
                                             cfg.max_hits)}


# ---------------------------------------------------------------------------------------
# Phase 5: the files the renderer reads

def _write_probes(out: Path, names: list, regions: dict, own: dict, textures: dict,
                  res: int) -> ProbeSet:
    """Write ``shadow_probes.npz`` (every object's region, occluded by all objects) and
    ``probes/<name>.npz`` (each object's own probes, occluded by the others); returns the
    shadow probes."""
    parts = []
    for r in names:
        ps = regions[r][0]
        o = occ.combine([textures[("region", r, j)] for j in names])            # [P, R, R]
        tex = np.zeros((ps.count, res, res, 4), np.float32)
        tex[..., 3] = o
        parts.append((ps, tex))
    shadow = ProbeSet(positions=np.concatenate([p.positions for p, _ in parts]),
                      normals=np.concatenate([p.normals for p, _ in parts]), res=res,
                      radius=max(p.radius for p, _ in parts),
                      texture=np.concatenate([t_ for _, t_ in parts]),
                      meta={"kind": "shadow regions", "objects": list(names)})
    shadow.save(out / "shadow_probes.npz")
    for r in names:
        ps = own[r][0]
        tex = ps.texture.copy()
        others = [textures[("own", r, j)] for j in names if j != r]
        if others:
            tex[..., 3] = occ.combine([tex[..., 3]] + others)
        ProbeSet(ps.positions, ps.normals, ps.res, ps.radius, texture=tex,
                 meta={**ps.meta, "occluders": [j for j in names if j != r]}
                 ).save(out / "probes" / f"{r}.npz")
    return shadow


def _apply_exposure(out: Path, world: _World, exposure) -> dict:
    """{name: (the exposure record, the PLY the renderer reads)}: each object's gain
    (``compose``'s ``exposure``) and, where it is not 1, ``objects/<name>.ply`` with the
    albedo × gain (clipped to 1; the share of clipped albedo values recorded)."""
    gains = {}
    for n in world.names:
        src = world.inputs.files[n]["ply"]
        g = (exposure.get(n) if isinstance(exposure, dict) else exposure) or xp.ExposureGain()
        if not (isinstance(g, xp.ExposureGain) or g == "grey-world"):
            raise ValueError(f"compose: exposure must be an ExposureGain, a dict of them, "
                             f"'grey-world' or None, got {g!r}")
        params = meta = None
        if g == "grey-world" or not g.is_identity:
            params, meta = load_ply(str(src), return_meta=True)
        if g == "grey-world":
            d = params.to_numpy()
            g = xp.gain_from_grey_world(d["albedo"], 1.0 / (1.0 + np.exp(-d["opacity_logit"])))
        record, ply = g.to_json(), src
        if not g.is_identity:
            d = params.to_numpy()
            a = d["albedo"].astype(np.float64) * np.asarray(g.gain)
            record["albedo_clipped"] = round(float((a > 1).mean()), 6)
            d["albedo"] = np.clip(a, 0.0, 1.0).astype(np.float32)
            ply = out / "objects" / f"{n}.ply"
            ply.parent.mkdir(parents=True, exist_ok=True)
            save_ply(type(params).from_numpy(**d), str(ply), color_space=meta.color_space)
            record["ply"] = f"objects/{n}.ply"
            if record["albedo_clipped"] > 0.01:
                log.warning("compose: %s: %.1f%% of the albedo values × the exposure gain "
                            "exceed 1 and are clipped", n, 100 * record["albedo_clipped"])
        gains[n] = (record, ply)
    return gains


def _write_manifest(out: Path, world: _World, objects: dict, lighting: dict,
                    cfg: ComposeConfig, gains: dict) -> None:
    """``composition.json`` (``data.comp_folder``) and ``composition.xml``."""
    scene_run, scene_ply = world.inputs.scene_run, world.inputs.scene_ply
    manifest = {
        "version": comp_folder.FORMAT_VERSION,
        "scene": {"run": str(scene_run.resolve()), "ply": str(scene_ply.resolve()),
                  "colour_space": world.scene_meta.color_space or "srgb",
                  **({"sky": str((scene_run / "background.exr").resolve())}
                     if (scene_run / "background.exr").is_file() else {})},
        "world_from_source": world.W.tolist(),
        "objects": {n: {"run": str(Path(objects[n]).resolve()),
                        "ply": str(Path(gains[n][1]).resolve()),
                        "placement": world.sims[n].matrix.tolist(), "envmap": f"env/{n}.exr",
                        "probes": f"probes/{n}.npz",
                        "bounds": [world.bounds[n][0].tolist(), world.bounds[n][1].tolist()],
                        "exposure": gains[n][0]}
                    for n in objects},
        "shadow_probes": "shadow_probes.npz", "lighting": lighting,
        "config": asdict(cfg)}
    atomic_write_text(out / comp_folder.MANIFEST, json.dumps(manifest, indent=1))
    comp_folder.write_xml(out / "composition.xml", out, manifest)


def _summary(timings: dict, shadow: ProbeSet, regions: dict, own: dict, cache: _Cache,
             culled: list, cfg: ComposeConfig) -> dict:
    """The ``edit.json`` record: timings, probe counts, which pairs were traced, reused or
    culled, and which other cached parts were recomputed."""
    res = cfg.shadow.res
    return {"timings": timings,
            "probes": {"shadow": shadow.count, "shadow_per_object": {r: regions[r][0].count for r in regions},
                       "object": {r: own[r][0].count for r in own}},
            "pairs": {"traced": [m for m in cache.misses if m.startswith("occ_") and m not in culled],
                      "culled": culled,
                      "reused": [h for h in cache.hits if h.startswith("occ_")]},
            "rays_per_probe": res * res * cfg.shadow.supersample ** 2,
            "recomputed": [m for m in cache.misses if not m.startswith("occ_")]}


def summary_text(summary: dict, cfg: ComposeConfig, out) -> str:
    """What ``comgs compose`` prints of a :func:`compose` summary: the timings, objects with
    fewer shadow probes than ``cfg`` asked (every facing scene point in the region is used),
    and the probe and pair counts."""
    t = summary["timings"]
    lines = [f"{'part':<20}{'seconds':>10}"]
    lines += [f"{k:<20}{t[k]:>10.2f}"
              for k in ("lighting", "probe_placement", "occlusion_tracing", "total")]
    for n, c in summary["probes"].get("shadow_per_object", {}).items():
        if c < cfg.shadow.count:
            lines.append(f"shadow probes of {n!r}: {c} of the {cfg.shadow.count} asked (every "
                         f"scene surface point facing it in its region has one)")
    pr = summary["pairs"]
    lines.append(f"{summary['probes']['shadow']} shadow probes; occlusion pairs traced "
                 f"{len(pr['traced'])}, reused {len(pr['reused'])}, culled "
                 f"{len(pr['culled'])}; wrote {out}")
    return "\n".join(lines)
