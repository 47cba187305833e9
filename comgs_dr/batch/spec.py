"""The jobs file of ``comgs batch`` (docs/batch.md): read, checked, paths resolved.

:func:`load_jobs` returns a :class:`Batch`: the scenes and objects (each reconstructed once,
however many jobs use it) and the jobs (a composition and its renders). Every error is a
:class:`JobsFileError` (a ValueError) naming the file and the entry, raised before anything
runs; a missing input file is not checked here: the job that needs it fails alone.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from comgs_dr.stages.compose import ComposeConfig, compose_config
from comgs_dr.stages.decompose import MaterialConfig
from comgs_dr.stages.estimate_light import PlacementEstimateConfig
from comgs_dr.stages.reconstruct import RadianceConfig
from comgs_dr.stages.render_comp import RenderCompConfig

TOP_KEYS = ("mitsuba_variant", "retries", "task_cpus", "scenes", "objects", "jobs")
# how step 1 loads the dataset (not RadianceConfig fields), as `comgs reconstruct` has them
LOAD_KEYS = ("preset", "resolution_scale", "white_background", "densify_scaled")
COMPOSE_KEYS = ("preset", "shadow_probes", "env", "exposure_gain", "white_patch", "grey_world")
RENDER_KEYS = ("cameras", "gt_dir", "shards")
# settings that name files: resolved against the jobs file's folder
PATH_SETTINGS = {"init": ".ply", "env": "", "weights": "", "scene_label": ".json",
                 "light_head": ".pt", "cameras": "", "gt_dir": "", "path": ".json",
                 "video": ""}


class JobsFileError(ValueError):
    """A jobs file ``comgs batch`` cannot run: its text names the file and the entry."""


@dataclass
class Source:
    """A scene or an object: reconstructed from ``data`` into ``out`` (step 1, and for an
    object step 2 into ``out/material``), or an existing run (``data`` None)."""
    kind: str                       # "scene" | "object"
    name: str
    out: str                        # the run folder
    data: str | None = None
    reconstruct: dict = field(default_factory=dict)    # RadianceConfig fields + LOAD_KEYS
    decompose: dict = field(default_factory=dict)      # MaterialConfig fields (objects)


@dataclass
class Render:
    """One ``render-comp`` of a job, split into ``shards`` tasks."""
    cameras: str | None = None
    gt_dir: str | None = None
    shards: int = 1
    settings: dict = field(default_factory=dict)       # RenderCompConfig fields


@dataclass
class Job:
    """A composition (``compose`` of ``objects`` in ``scene`` at ``placement`` into ``out``)
    and its renders; with ``comp`` an existing composition, only rendered."""
    name: str
    out: str
    scene: str | None = None
    objects: dict = field(default_factory=dict)        # {name in transform.json: object}
    placement: str | None = None
    compose: dict = field(default_factory=dict)
    renders: list = field(default_factory=list)
    existing: bool = False                             # `comp:` given: nothing composed


@dataclass
class Batch:
    path: str
    scenes: dict
    objects: dict
    jobs: list
    mitsuba_variant: str = "auto"
    retries: int = 3
    task_cpus: int = 1


def load_jobs(path) -> Batch:
    """The checked :class:`Batch` of a jobs file (YAML, or JSON, which YAML reads)."""
    import yaml
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: jobs file not found")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise JobsFileError(f"{path}: not valid YAML: {e}") from None
    return parse_jobs(doc, path)


def parse_jobs(doc, path) -> Batch:
    """:func:`load_jobs` of an already parsed document; paths relative to ``path``'s folder."""
    path = Path(path)
    root = path.resolve().parent

    def bad(where: str, msg: str):
        return JobsFileError(f"{path}: {where}: {msg}")

    _mapping(doc, "the file", bad, required=("jobs",), allowed=TOP_KEYS)
    scenes = {n: _source("scene", n, e, root, bad) for n, e in _entries(doc, "scenes", bad)}
    objects = {n: _source("object", n, e, root, bad) for n, e in _entries(doc, "objects", bad)}
    runs = {}
    for s in [*scenes.values(), *objects.values()]:
        other = runs.setdefault(s.out, s)
        if other is not s:
            raise bad(f"{s.kind}s.{s.name}", f"its run folder {s.out} is also "
                      f"{other.kind}s.{other.name}'s: one folder per scene or object")
    jobs_doc = doc["jobs"]
    if not isinstance(jobs_doc, list) or not jobs_doc:
        raise bad("jobs", "must be a non-empty list of jobs")
    jobs, outs = [], {}
    for i, e in enumerate(jobs_doc):
        job = _job(i, e, scenes, objects, root, bad)
        if job.name in {j.name for j in jobs}:
            raise bad(f"jobs[{i}]", f"name {job.name!r} is also an earlier job's")
        if job.out in outs and not (job.existing and jobs[outs[job.out]].existing):
            raise bad(f"jobs[{i}] ({job.name})", f"out {job.out} is also "
                      f"{jobs[outs[job.out]].name}'s: one composition folder per job")
        if job.out in runs:
            raise bad(f"jobs[{i}] ({job.name})", f"out {job.out} is a run folder")
        outs.setdefault(job.out, i)
        jobs.append(job)
    variant = doc.get("mitsuba_variant", "auto")
    if not isinstance(variant, str):
        raise bad("mitsuba_variant", f"must be a variant name (auto, llvm_ad_rgb, "
                  f"cuda_ad_rgb), got {variant!r}")
    retries, cpus = doc.get("retries", 3), doc.get("task_cpus", 1)
    for key, v, low in (("retries", retries, 0), ("task_cpus", cpus, 1)):
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise bad(key, f"must be an integer >= {low}, got {v!r}")
    return Batch(str(path), scenes, objects, jobs, variant, retries, cpus)


# --------------------------------------------------------------------------- entries

def _mapping(e, where, bad, required=(), allowed=None) -> dict:
    if not isinstance(e, dict):
        raise bad(where, f"must be a mapping, got {type(e).__name__}")
    for k in required:
        if k not in e:
            raise bad(where, f"{k!r} is missing")
    if allowed is not None:
        unknown = [k for k in e if k not in allowed]
        if unknown:
            raise bad(where, f"unknown key {unknown[0]!r} (known: {', '.join(allowed)})")
    return e


def _entries(doc, key, bad):
    d = doc.get(key) or {}
    _mapping(d, key, bad)
    for name, e in d.items():
        if not isinstance(name, str) or not name:
            raise bad(key, f"names must be non-empty strings, got {name!r}")
        yield name, e


def _path(root: Path, v, where, bad) -> str:
    if not isinstance(v, str) or not v:
        raise bad(where, f"must be a path, got {v!r}")
    p = Path(v).expanduser()
    return str(p if p.is_absolute() else root / p)


def _settings(d: dict, root: Path, where: str, bad) -> dict:
    """``d`` with the file settings (PATH_SETTINGS) made absolute."""
    out = dict(d)
    for k, suffix in PATH_SETTINGS.items():
        v = out.get(k)
        if isinstance(v, str) and (not suffix or v.lower().endswith(suffix)):
            out[k] = _path(root, v, f"{where}.{k}", bad)
    return out


def _fields(cls) -> set:
    return {f.name for f in dataclasses.fields(cls)}


def _check_config(where, bad, make):
    try:
        return make()
    except FileNotFoundError:       # an input file: the job fails alone, when it runs
        return None
    except (TypeError, ValueError) as e:
        raise bad(where, str(e)) from None


def _source(kind, name, e, root, bad) -> Source:
    where = f"{kind}s.{name}"
    keys = ("data", "out", "run", "reconstruct") + (("decompose",) if kind == "object" else ())
    _mapping(e, where, bad, allowed=keys)
    if ("run" in e) == ("data" in e):
        raise bad(where, "give data (a dataset to reconstruct, with out) or run (an existing "
                  "run folder), not both or neither")
    if "run" in e:
        if "out" in e or "reconstruct" in e or "decompose" in e:
            raise bad(where, "an existing run (run:) takes no out, reconstruct or decompose")
        return Source(kind, name, _path(root, e["run"], f"{where}.run", bad))
    if "out" not in e:
        raise bad(where, "'out' is missing (the run folder the reconstruction writes)")
    rec = _mapping(e.get("reconstruct") or {}, f"{where}.reconstruct", bad,
                   allowed=LOAD_KEYS + tuple(sorted(_fields(RadianceConfig) - {"preset",
                                                                                "densify"})))
    rec = _settings(rec, root, f"{where}.reconstruct", bad)
    preset = rec.get("preset", kind)
    cfg = {k: v for k, v in rec.items() if k not in LOAD_KEYS}
    _check_config(f"{where}.reconstruct", bad, lambda: RadianceConfig.from_preset(preset, **cfg))
    if rec.get("resolution_scale", 1) not in (1, 2, 4, 8):
        raise bad(f"{where}.reconstruct.resolution_scale", "must be 1, 2, 4 or 8")
    dec = _mapping(e.get("decompose") or {}, f"{where}.decompose", bad,
                   allowed=tuple(sorted(_fields(MaterialConfig))))
    dec = _settings(dec, root, f"{where}.decompose", bad)
    _check_config(f"{where}.decompose", bad, lambda: MaterialConfig(**dec))
    return Source(kind, name, _path(root, e["out"], f"{where}.out", bad),
                  _path(root, e["data"], f"{where}.data", bad), rec, dec)


def _job(i, e, scenes, objects, root, bad) -> Job:
    where = f"jobs[{i}]"
    _mapping(e, where, bad, allowed=("name", "scene", "objects", "placement", "out", "comp",
                                     "compose", "render"))
    name = e.get("name", f"job{i}")
    if not isinstance(name, str) or not name:
        raise bad(where, f"name must be a non-empty string, got {name!r}")
    where = f"jobs[{i}] ({name})"
    renders = e.get("render") or []
    renders = [renders] if isinstance(renders, dict) else renders
    if not isinstance(renders, list):
        raise bad(f"{where}.render", "must be a mapping or a list of them")
    renders = [_render(r, root, f"{where}.render[{k}]", bad) for k, r in enumerate(renders)]
    if "comp" in e:                 # an existing composition: only rendered
        extra = [k for k in ("scene", "objects", "placement", "out", "compose") if k in e]
        if extra:
            raise bad(where, f"comp (an existing composition) takes no {extra[0]}")
        if not renders:
            raise bad(where, "comp (an existing composition) needs render")
        return Job(name, _path(root, e["comp"], f"{where}.comp", bad), renders=renders,
                   existing=True)
    _mapping(e, where, bad, required=("scene", "objects", "placement", "out"))
    if e["scene"] not in scenes:
        raise bad(f"{where}.scene", f"{e['scene']!r} is not in scenes "
                  f"({', '.join(scenes) or 'none'})")
    objs = e["objects"]
    objs = {o: o for o in objs} if isinstance(objs, list) else objs
    if not isinstance(objs, dict) or not objs:
        raise bad(f"{where}.objects", "must be a list of objects, or a mapping {name in the "
                  "placement: object}")
    for k, o in objs.items():
        if o not in objects:
            raise bad(f"{where}.objects", f"{o!r} is not in objects "
                      f"({', '.join(objects) or 'none'})")
    comp = _mapping(e.get("compose") or {}, f"{where}.compose", bad,
                    allowed=COMPOSE_KEYS + tuple(sorted(_fields(ComposeConfig) - {"shadow"}))
                    + tuple(sorted(_fields(PlacementEstimateConfig))))
    comp = _settings(comp, root, f"{where}.compose", bad)
    if comp.get("white_patch") is not None:
        wp = comp["white_patch"]
        if not isinstance(wp, list) or len(wp) != 2 or not all(isinstance(s, str) for s in wp):
            raise bad(f"{where}.compose.white_patch", "must be [OBJECT_PHOTO[:box], "
                      "SCENE_PHOTO[:box]]")
        comp["white_patch"] = [_path(root, s, f"{where}.compose.white_patch", bad)
                               for s in wp]
    given = [k for k in ("exposure_gain", "white_patch", "grey_world") if comp.get(k)]
    if len(given) > 1:
        raise bad(f"{where}.compose", f"give one of exposure_gain, white_patch, grey_world, "
                  f"not {' and '.join(given)}")
    cfg = {k: v for k, v in comp.items() if k in _fields(ComposeConfig)}
    _check_config(f"{where}.compose", bad, lambda: compose_config(
        comp.get("preset", "default"), comp.get("shadow_probes"), **cfg))
    est = [k for k in comp if k in _fields(PlacementEstimateConfig)]
    if comp.get("env") and est:
        raise bad(f"{where}.compose", f"{est[0]} sets up the lighting estimation; with env "
                  f"the map is the light and nothing is estimated")
    return Job(name, _path(root, e["out"], f"{where}.out", bad), e["scene"], dict(objs),
               _path(root, e["placement"], f"{where}.placement", bad), comp, renders)


def _render(r, root, where, bad) -> Render:
    allowed = RENDER_KEYS + tuple(f.name for f in dataclasses.fields(RenderCompConfig))
    _mapping(r, where, bad, allowed=allowed)
    r = _settings(r, root, where, bad)
    shards = r.get("shards", 1)
    if isinstance(shards, bool) or not isinstance(shards, int) or shards < 1:
        raise bad(f"{where}.shards", f"must be an integer >= 1, got {shards!r}")
    settings = {k: v for k, v in r.items() if k not in RENDER_KEYS}
    if isinstance(settings.get("res"), list):
        settings["res"] = tuple(settings["res"])
    _check_config(where, bad, lambda: RenderCompConfig(**settings).validate())
    if r.get("cameras") is None and settings.get("path") is None:
        raise bad(where, "give cameras (a transforms.json or a dataset folder) or path "
                  "(orbit, spiral or a transforms.json)")
    return Render(r.get("cameras"), r.get("gt_dir"), shards, settings)
