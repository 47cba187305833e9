"""``comgs compose``: the edit stage of a composition (paper, "Occlusion Caching").

Inputs: a step-1 scene run, one step-2 object run per object, placements
(``transform.json``) and the lighting (one equirect/octahedral map for every object, or an
``estimator(position, name) -> equirect radiance`` run at each object's centre, e.g.
``comgs estimate-light``). Output, in ``COMP_DIR``:

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
  ``edit.json`` (timings of lighting, probe placement and occlusion tracing; pair counts).
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np
from tqdm.auto import tqdm

from comgs_dr.data import comp_folder
from comgs_dr.surfels.params import object_bounds
from comgs_dr.lighting import envmap as em
from comgs_dr.sops import occlusion as occ
from comgs_dr.sops.placement import PlacementConfig, fuse_depth, render_geometry
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.surfels.io import load_ply
from comgs_dr.surfels.shape import SurfelShapeBase
from comgs_dr.surfels.transform import transform_surfels
from comgs_dr.core import runlog
from comgs_dr.core.similarity import read_placements
from comgs_dr.train.run import load_run_dataset, read_run_info, select_views
from comgs_dr.train.checkpoint import atomic_write_text

log = logging.getLogger(__name__)


@dataclass
class ComposeConfig:
    """Settings of :func:`compose` (sec. 4.1: 10k shadow probes, 6× region; 32² texels)."""
    shadow: occ.ShadowConfig = field(default_factory=occ.ShadowConfig)
    env_res: int = 256               # octahedral texels per side of each object's map
    scene_views: int = 16            # scene views rendered for the surface points
    min_consistent: int = 2          # other views that must agree on a surface point
    max_hits: int = 32               # surfels composited per occlusion ray
    seed: int = 0


PRESETS = {"default": ComposeConfig(),
           "fast": ComposeConfig(shadow=occ.ShadowConfig(count=2000, res=16),
                                 scene_views=8)}


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


def _lighting(names, centres, env, estimator, res, out: Path, timings: dict) -> dict:
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


def compose(scene_run, objects: dict, placement, out, env=None, estimator=None,
            cfg: ComposeConfig = ComposeConfig(), progress: bool = True) -> dict:
    """Build (or update) a composition folder; returns the ``edit.json`` summary.

    ``objects``: {name: step-2 run folder}; ``placement``: a ``transform.json`` path or
    {name: Similarity}; ``env``: one map for all objects (equirect Z-up or octahedral
    EXR) — or ``estimator``: callable(world position [3], object name) -> equirect
    radiance [H, W, 3] (the name lets it keep its own record of each estimate).
    A folder this call created is removed again when it fails before writing a file.
    """
    out = Path(out)
    created = not out.exists()
    try:
        return _compose(scene_run, objects, placement, out, env, estimator, cfg, progress)
    except BaseException:
        if created and out.is_dir():
            try:
                for d in sorted(out.rglob("*"), reverse=True):   # empty sub-folders first
                    if d.is_dir() and not any(d.iterdir()):
                        d.rmdir()
                if not any(out.iterdir()):
                    out.rmdir()
            except OSError:                 # the original error matters, not the cleanup's
                pass
        raise


MIN_RELATIVE_SIZE = 1e-4    # a placed object smaller than this × the scene: a wrong scale


def _compose(scene_run, objects, placement, out: Path, env, estimator, cfg, progress) -> dict:
    t_all = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    timings = {}
    scene_run = Path(scene_run)
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

    t = time.perf_counter()
    data = load_run_dataset(scene_run, info, pixels=False)     # cameras only
    W = np.asarray(data.world_from_source, np.float64)
    scene_params, scene_meta = load_ply(str(scene_ply), return_meta=True)
    placed, sims, bounds = {}, {}, {}
    for n in objects:
        s0 = placements[n]
        sims[n] = type(s0)(s0.scale, W[:3, :3] @ s0.rotation, W[:3, :3] @ s0.translation + W[:3, 3])
        placed[n] = transform_surfels(load_ply(str(files[n]["ply"])), sims[n])
        bounds[n] = object_bounds(placed[n])
    centres = {n: (bounds[n][0] + bounds[n][1]) / 2 for n in objects}
    scene_size = float(np.linalg.norm(np.subtract(*object_bounds(scene_params)[::-1])))
    for n in objects:
        size = float(np.linalg.norm(bounds[n][1] - bounds[n][0]))
        if not size > MIN_RELATIVE_SIZE * scene_size:
            raise ValueError(f"compose: object {n!r} placed at scale {sims[n].scale:.3g} is "
                             f"{size:.3g} units across, {size / scene_size:.1e} of the scene's "
                             f"{scene_size:.3g}: check its placement's scale")
    timings["load"] = time.perf_counter() - t

    light = _lighting(list(objects), centres, env, estimator, cfg.env_res, out, timings)

    cache = _Cache(out)
    t = time.perf_counter()
    scene_key = _key(_stat(scene_ply), W.tolist(), cfg.scene_views, cfg.min_consistent)
    views = select_views(data.train, cfg.scene_views)

    def surface():
        pc = PlacementConfig(min_consistent=cfg.min_consistent, max_views=len(views))
        bufs = render_geometry(scene_params, [v.camera for v in views])
        fused = fuse_depth([v.camera for v in views], bufs, pc)
        return {"points": fused.points.astype(np.float32), "normals": fused.normals.astype(np.float32)}
    surf = cache.get("scene_surface", scene_key, surface)
    regions = {}
    for i, n in enumerate(objects):
        rkey = _key(scene_key, np.round(bounds[n], 6).tolist(), asdict(cfg.shadow), cfg.seed)

        def make(n=n, i=i):
            ps = occ.shadow_region_probes(surf["points"], surf["normals"], *bounds[n], cfg.shadow,
                                          cfg.seed + i, n)
            return {"positions": ps.positions, "normals": ps.normals,
                    "radius": np.float64(ps.radius)}
        r = cache.get(f"region_{n}", rkey, make)
        regions[n] = (ProbeSet(r["positions"], r["normals"], cfg.shadow.res, float(r["radius"])),
                      rkey)
    own = {}
    for n in objects:
        okey = _key(_stat(files[n]["probes"]), sims[n].matrix.round(9).tolist())

        def make_own(n=n):
            ps = occ.transform_probes(ProbeSet.load(files[n]["probes"]), sims[n])
            return {"positions": ps.positions, "normals": ps.normals, "texture": ps.texture,
                    "radius": np.float64(ps.radius), "res": np.int64(ps.res)}
        o = cache.get(f"own_{n}", okey, make_own)
        own[n] = (ProbeSet(o["positions"], o["normals"], int(o["res"]), float(o["radius"]),
                           texture=o["texture"]), okey)
    timings["probe_placement"] = time.perf_counter() - t

    # occlusion of every receiver probe set by every (other) object, cached per pair
    t = time.perf_counter()
    occluder_keys = {n: _key(_stat(files[n]["ply"]), sims[n].matrix.round(9).tolist(),
                             cfg.max_hits, cfg.shadow.supersample) for n in objects}
    scenes = {}

    def occluder_scene(n):
        if n not in scenes:
            scenes[n] = mi.load_dict({"type": "scene", n: SurfelShapeBase.from_params(placed[n], id=n)})
        return scenes[n]
    pairs = [("region", r, j) for r in objects for j in objects] + \
            [("own", r, j) for r in objects for j in objects if j != r]
    culled, textures = [], {}
    bar = tqdm(pairs, desc="occlusion", unit="pair", disable=not progress)
    for kind, r, j in bar:
        probes, rkey = (regions if kind == "region" else own)[r]
        name = f"occ_{kind}_{r}__{j}"
        lo, hi = bounds[j]
        sphere_r = float(np.linalg.norm(hi - lo)) / 2

        def make_occ(probes=probes, j=j, lo=lo, hi=hi, sphere_r=sphere_r, name=name):
            if not occ.can_occlude(probes, (lo + hi) / 2, sphere_r):
                culled.append(name)
                return {"occlusion": np.zeros((probes.count, probes.res, probes.res), np.float32)}
            return {"occlusion": occ.trace_occlusion(probes, occluder_scene(j),
                                                     cfg.shadow.supersample, cfg.max_hits)}
        textures[(kind, r, j)] = cache.get(name, _key(rkey, occluder_keys[j]), make_occ)["occlusion"]
    bar.close()
    timings["occlusion_tracing"] = time.perf_counter() - t

    # assemble what the renderer reads
    t = time.perf_counter()
    res = cfg.shadow.res
    parts = []
    for r in objects:
        ps = regions[r][0]
        o = occ.combine([textures[("region", r, j)] for j in objects])          # [P, R, R]
        tex = np.zeros((ps.count, res, res, 4), np.float32)
        tex[..., 3] = o
        parts.append((ps, tex))
    shadow = ProbeSet(positions=np.concatenate([p.positions for p, _ in parts]),
                      normals=np.concatenate([p.normals for p, _ in parts]), res=res,
                      radius=max(p.radius for p, _ in parts),
                      texture=np.concatenate([t_ for _, t_ in parts]),
                      meta={"kind": "shadow regions", "objects": list(objects)})
    shadow.save(out / "shadow_probes.npz")
    for r in objects:
        ps = own[r][0]
        tex = ps.texture.copy()
        others = [textures[("own", r, j)] for j in objects if j != r]
        if others:
            tex[..., 3] = occ.combine([tex[..., 3]] + others)
        ProbeSet(ps.positions, ps.normals, ps.res, ps.radius, texture=tex,
                 meta={**ps.meta, "occluders": [j for j in objects if j != r]}
                 ).save(out / "probes" / f"{r}.npz")
    manifest = {
        "version": comp_folder.FORMAT_VERSION,
        "scene": {"run": str(scene_run.resolve()), "ply": str(scene_ply.resolve()),
                  "colour_space": scene_meta.color_space or "srgb",
                  **({"sky": str((scene_run / "background.exr").resolve())}
                     if (scene_run / "background.exr").is_file() else {})},
        "world_from_source": W.tolist(),
        "objects": {n: {"run": str(Path(objects[n]).resolve()), "ply": str(files[n]["ply"].resolve()),
                        "placement": sims[n].matrix.tolist(), "envmap": f"env/{n}.exr",
                        "probes": f"probes/{n}.npz",
                        "bounds": [bounds[n][0].tolist(), bounds[n][1].tolist()]}
                    for n in objects},
        "shadow_probes": "shadow_probes.npz", "lighting": light["source"],
        "config": asdict(cfg)}
    atomic_write_text(out / comp_folder.MANIFEST, json.dumps(manifest, indent=1))
    comp_folder.write_xml(out / "composition.xml", out, manifest)
    timings["write"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    summary = {"timings": timings,
               "probes": {"shadow": shadow.count, "shadow_per_object": {r: regions[r][0].count for r in objects},
                          "object": {r: own[r][0].count for r in objects}},
               "pairs": {"traced": [m for m in cache.misses if m.startswith("occ_") and m not in culled],
                         "culled": culled,
                         "reused": [h for h in cache.hits if h.startswith("occ_")]},
               "rays_per_probe": res * res * cfg.shadow.supersample ** 2,
               "recomputed": [m for m in cache.misses if not m.startswith("occ_")]}
    atomic_write_text(out / "edit.json", json.dumps(runlog.json_safe(summary), indent=1,
                                                     allow_nan=False))
    runlog.rewrite(out, runlog.part_records("compose", timings, shadow_probes=shadow.count))
    return summary
