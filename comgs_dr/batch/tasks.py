"""The tasks of a batch, each run in a Ray worker process (``graph`` wraps them with
``ray.remote``): one stage function called in-process, as its ``comgs`` command calls it.

Every task first selects the Mitsuba variant and Dr.Jit's thread count (a worker is a
fresh process with its own Dr.Jit state) and leaves an attempt record
(``WORK/attempts/<task>/<ns>-<pid>.json``: a retried task has several). Inputs and outputs
are run folders on the shared file system; tasks hand each other only small dicts.
"""
from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

from comgs_dr.batch.spec import Job, Render, Source


def start(work, key: str, mi_variant: str, cpus: int) -> None:
    """The start of every attempt: variant, thread count, attempt record."""
    import drjit as dr

    from comgs_dr import set_variant
    set_variant(mi_variant)
    dr.set_thread_count(int(cpus))
    d = Path(work) / "attempts" / key
    d.mkdir(parents=True, exist_ok=True)
    rec = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
    (d / f"{time.time_ns()}-{os.getpid()}.json").write_text(json.dumps(rec))


def reconstruct(src: Source, mi_variant: str, cpus: int, work, key: str) -> dict:
    """Step 1 of a scene or an object, as ``comgs reconstruct DATA --out OUT`` (a dataset
    folder: photos go through ``comgs sfm`` first)."""
    start(work, key, mi_variant, cpus)
    from comgs_dr.data.load import load_dataset
    from comgs_dr.stages.reconstruct import (RadianceConfig, scaled_density_schedule,
                                             train_radiance)
    from comgs_dr.train.run import write_run_info
    t = time.perf_counter()
    kw = dict(src.reconstruct)
    preset = kw.pop("preset", src.kind)
    scale, white = kw.pop("resolution_scale", 1), kw.pop("white_background", False)
    if kw.pop("densify_scaled", False):
        kw["densify"] = scaled_density_schedule(kw.get("iterations", RadianceConfig.iterations))
    cfg = RadianceConfig.from_preset(preset, **kw)
    data = load_dataset(src.data, white_background=white, resolution_scale=scale)
    write_run_info(src.out, src.data, preset, scale, white)
    s = train_radiance(data, src.out, cfg, progress=False)
    return {"run": src.out, "psnr_test": s.get("psnr_test"),
            "seconds": round(time.perf_counter() - t, 2)}


def decompose(src: Source, mi_variant: str, cpus: int, work, key: str, step1: dict) -> dict:
    """Step 2 of an object, as ``comgs decompose RUN`` (into RUN/material)."""
    start(work, key, mi_variant, cpus)
    from comgs_dr.stages.decompose import MaterialConfig, train_material
    t = time.perf_counter()
    s = train_material(src.out, None, MaterialConfig(**src.decompose), progress=False)
    return {"run": src.out, "psnr_test": s.get("psnr_test"),
            "seconds": round(time.perf_counter() - t, 2)}


def compose(job: Job, scene: dict, mi_variant: str, cpus: int, work, key: str,
            *objects: dict) -> dict:
    """``comgs compose SCENE_RUN --object NAME=RUN ... --placement P --out OUT``;
    ``scene``, ``objects``: the scene's and the objects' task results ({"run": folder}),
    the objects in the order of ``job.objects``."""
    start(work, key, mi_variant, cpus)
    from comgs_dr.data.exposure import resolve_exposure
    from comgs_dr.stages.compose import ComposeConfig, compose as compose_stage, compose_config
    from comgs_dr.stages.estimate_light import PlacementEstimateConfig, placement_estimator
    t = time.perf_counter()
    scene_run, c = scene["run"], job.compose
    cfg = compose_config(c.get("preset", "default"), c.get("shadow_probes"),
                         **{k: v for k, v in c.items() if k in ComposeConfig.__dataclass_fields__})
    gain, patch = c.get("exposure_gain"), c.get("white_patch")
    exposure = ("grey-world" if c.get("grey_world") else
                resolve_exposure(gain, patch) if gain is not None or patch is not None else None)
    est = {k: v for k, v in c.items() if k in PlacementEstimateConfig.__dataclass_fields__}
    estimator = placement_estimator(scene_run, job.out, c.get("env"), **est)
    runs = {name: r["run"] for name, r in zip(job.objects, objects)}
    s = compose_stage(scene_run, runs, job.placement, job.out, env=c.get("env"),
                      estimator=estimator, cfg=cfg, progress=False,
                      **({"exposure": exposure} if exposure is not None else {}))
    return {"comp": job.out, "seconds": round(time.perf_counter() - t, 2),
            "timings": s.get("timings")}


# --------------------------------------------------------------------------- render-comp

def _render_args(render: Render) -> dict:
    s = dict(render.settings)
    return dict(variant=s.get("variant", "sop"), materials=s.get("materials"),
                res=s.get("res"), rays=s.get("rays"), seed=s.get("seed", 0),
                path=s.get("path"), frames=s.get("frames"))


def read_records(records) -> dict:
    """{frame name: record} of the frames a shard has finished (``records/<name>.json``)."""
    out = {}
    for p in sorted(Path(records).glob("*.json")):
        out[p.stem] = json.loads(p.read_text())
    return out


def render_shard(comp_dir: str, render: Render, shard: int, shards: int, records: str,
                 mi_variant: str, cpus: int, work, key: str, *after) -> dict:
    """Frames ``shard, shard + shards, ...`` of ``comgs render-comp`` (each with the seed
    the single process gives it). After each frame's PNG is in place its record is written
    to ``records/<name>.json``; a retried attempt skips the frames recorded there, so a
    killed worker loses no frame and writes none twice. ``after``: the compose result the
    render waits for (unused)."""
    start(work, key, mi_variant, cpus)
    from comgs_dr.core import runlog
    from comgs_dr.stages.render_comp import render_comp
    from comgs_dr.train.checkpoint import atomic_write_text
    records = Path(records)
    records.mkdir(parents=True, exist_ok=True)
    done = read_records(records)
    rendered = []

    def on_frame(i, rec):
        p = records / f"{rec['name']}.json"
        if p.exists():                  # (a frame rendered twice: counted, never expected)
            (records.parent / f"{records.name}.twice").mkdir(exist_ok=True)
            (records.parent / f"{records.name}.twice" / f"{rec['name']}-{time.time_ns()}").touch()
        atomic_write_text(p, json.dumps(runlog.json_safe({**rec, "index": i})))
        rendered.append(rec["name"])

    t = time.perf_counter()
    s = render_comp(comp_dir, render.cameras, gt_dir=render.gt_dir, progress=False,
                    frame_indices=slice(shard, None, shards), done=done, on_frame=on_frame,
                    **_render_args(render))
    return {"frames": [f["name"] for f in s["per_frame"]], "rendered": rendered,
            "skipped": len(s["per_frame"]) - len(rendered),
            "seconds": round(time.perf_counter() - t, 2)}


def render_merge(comp_dir: str, render: Render, records: str, mi_variant: str, cpus: int,
                 work, key: str, *shards: dict) -> dict:
    """The summary of a sharded render, as the single process writes it
    (``metrics_<variant>.json`` with ground truth, ``path_<variant>.json`` for a path, the
    video, ``render_<variant>.metrics.jsonl``): ``render_comp`` with every frame done (a
    frame no shard recorded is rendered here)."""
    start(work, key, mi_variant, cpus)
    from comgs_dr.stages.render_comp import render_comp
    done = read_records(records)
    rendered = []
    s = render_comp(comp_dir, render.cameras, gt_dir=render.gt_dir, progress=False,
                    done=done, on_frame=lambda i, rec: rendered.append(rec["name"]),
                    video=render.settings.get("video"), fps=render.settings.get("fps", 24.0),
                    **_render_args(render))
    s["frame_names"] = [f["name"] for f in s.pop("per_frame")]
    s["rendered_in_merge"] = rendered
    return s
