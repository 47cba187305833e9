"""The Ray task graph of a batch (:func:`run_batch`) and of a sharded ``render-comp``
(:func:`render_sharded`).

Graph: every scene and object with ``data`` is reconstructed once (an object then
decomposed), however many jobs use it; each job's ``compose`` waits for its scene and
objects; each render of a job is ``shards`` tasks (frames k, k + shards, ...) and a merge
that writes the summary files. A task that raises (bad input) is not retried and fails
the tasks that wait for it, so a job fails with its first failed task's error and the
other jobs go on; a task whose worker dies is retried (``retries``, Ray's ``max_retries``).

Inputs and outputs go through the shared file system (the run and composition folders the
single commands write), not Ray's object store: the stages read and write folders (a run
is checkpoint, point cloud, material textures, probes; a composition records its runs'
paths), every output must land where the single command writes it, and a retried task
resumes from what its killed attempt left (a step's checkpoint, a shard's finished frames).
Tasks pass each other only small dicts through the object store.
"""
from __future__ import annotations

import json
import shutil
import time
import traceback
from pathlib import Path

from comgs_dr.batch import tasks
from comgs_dr.batch.spec import Batch, Render


def init_ray(address: str | None = None, num_cpus: int | None = None) -> bool:
    """Connect to the Ray cluster at ``address`` ("auto": the one ``ray start`` made here),
    or start a local instance (``address`` None or "local"; ``num_cpus`` None: every core).
    Returns whether this call started or connected (and so should shut down)."""
    try:
        import ray
    except ImportError:
        raise ImportError("comgs batch and --ray need Ray: pip install -e .[cpu] "
                          "(ray==2.60.0)") from None
    if ray.is_initialized():
        return False
    if address in (None, "local"):
        ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=True)
    elif num_cpus is not None:
        raise ValueError(f"--num-cpus sizes a local Ray instance; the cluster at {address} "
                         f"has its own (`ray start --num-cpus`)")
    else:
        ray.init(address=address, log_to_driver=True)
    return True


def _remote(fn, key: str, cpus: int, retries: int):
    import ray
    return ray.remote(fn).options(name=key, num_cpus=cpus, max_retries=retries,
                                  retry_exceptions=False)


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _submit_render(comp_dir: str, render: Render, label: str, work: Path, mi_variant: str,
                   cpus: int, retries: int, after: list) -> tuple[list, object]:
    """The shard tasks and the merge task of one render; returns ([(key, ref)], merge)."""
    records = work / "records" / label
    shutil.rmtree(records, ignore_errors=True)          # a fresh render: no earlier records
    shutil.rmtree(records.parent / f"{records.name}.twice", ignore_errors=True)
    n = render.shards
    shards = []
    for k in range(n):
        key = f"{label}.shard{k}of{n}"
        shards.append((key, _remote(tasks.render_shard, key, cpus, retries).remote(
            comp_dir, render, k, n, str(records), mi_variant, cpus, str(work), key, *after)))
    key = f"{label}.merge"
    merge = _remote(tasks.render_merge, key, cpus, retries).remote(
        comp_dir, render, str(records), mi_variant, cpus, str(work), key,
        *[r for _, r in shards])
    return shards + [(key, merge)], merge


def run_batch(batch: Batch, address: str | None = None, num_cpus: int | None = None,
              work=None, say=print) -> dict:
    """Run every job of ``batch`` on Ray; returns the summary (also written to
    ``WORK/summary.json``; ``work`` None: ``<jobs file>.batch/`` beside it)."""
    import ray
    jobs_file = Path(batch.path)
    work = Path(work) if work else jobs_file.resolve().with_name(jobs_file.stem + ".batch")
    shutil.rmtree(work / "attempts", ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    started = init_ray(address, num_cpus)
    t0 = time.perf_counter()
    mv, cpus, retries = batch.mitsuba_variant, batch.task_cpus, batch.retries
    try:
        refs = {}                               # task key -> ref
        deps = {}                               # task key -> the keys it waits for
        source = {}                             # (kind, name) -> (ref or run path, keys)
        for kind, group in (("scene", batch.scenes), ("object", batch.objects)):
            for name, src in group.items():
                if src.data is None:            # an existing run
                    source[kind, name] = ({"run": src.out}, [])
                    continue
                key = f"{kind}-{_safe(name)}.reconstruct"
                refs[key] = _remote(tasks.reconstruct, key, cpus, retries).remote(
                    src, mv, cpus, str(work), key)
                deps[key], last = [], key
                if kind == "object":
                    k2 = f"object-{_safe(name)}.decompose"
                    refs[k2] = _remote(tasks.decompose, k2, cpus, retries).remote(
                        src, mv, cpus, str(work), k2, refs[key])
                    deps[k2], last = [key], k2
                source[kind, name] = (refs[last], [last])
        job_tasks = {}                          # job name -> its keys, in order
        job_outs = {}
        for job in batch.jobs:
            label = f"job-{_safe(job.name)}"
            keys, after = [], []
            if not job.existing:
                scene_ref, scene_keys = source["scene", job.scene]
                obj = [source["object", o] for o in job.objects.values()]
                key = f"{label}.compose"
                refs[key] = _remote(tasks.compose, key, cpus, retries).remote(
                    job, scene_ref, mv, cpus, str(work), key, *[r for r, _ in obj])
                deps[key] = scene_keys + [k for _, ks in obj for k in ks]
                keys.append(key)
                after = [refs[key]]
            merges = []
            for i, render in enumerate(job.renders):
                sub, merge = _submit_render(job.out, render, f"{label}.render{i}", work, mv,
                                            cpus, retries, after)
                for k, r in sub:
                    refs[k] = r
                    deps[k] = keys[:1]
                keys += [k for k, _ in sub]
                merges.append(sub[-1][0])
            job_tasks[job.name] = keys
            job_outs[job.name] = merges
        results, errors = _wait_all(refs, say)
    finally:
        if started:
            ray.shutdown()
    summary = _summary(batch, work, refs, deps, job_tasks, job_outs, results, errors,
                       time.perf_counter() - t0)
    (work / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def _wait_all(refs: dict, say) -> tuple[dict, dict]:
    """Wait for every task; {key: result}, {key: error text} (the task's own exception)."""
    import ray
    by_ref = {r: k for k, r in refs.items()}
    pending, results, errors = list(refs.values()), {}, {}
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        key = by_ref[ready[0]]
        try:
            results[key] = ray.get(ready[0])
            say(f"[batch] {key}: done" + (f" in {results[key]['seconds']} s"
                                          if isinstance(results[key].get("seconds"), float)
                                          else ""))
        except Exception as e:                  # noqa: BLE001 - every failure is reported
            errors[key] = _error_text(e)
            say(f"[batch] {key}: failed: {errors[key]}")
    return results, errors


def _error_text(e: BaseException) -> str:
    """``Type: message`` of the exception a task raised (Ray wraps it in RayTaskError)."""
    cause = getattr(e, "cause", None)
    e = cause if isinstance(cause, BaseException) else e
    return f"{type(e).__name__}: {' '.join(str(e).split())}"


def attempts(work) -> dict:
    """{task key: attempts started} of the attempt records under ``WORK/attempts``."""
    root = Path(work) / "attempts"
    return {d.name: len(list(d.glob("*.json"))) for d in sorted(root.iterdir())} \
        if root.is_dir() else {}


def _summary(batch, work, refs, deps, job_tasks, job_outs, results, errors, seconds) -> dict:
    tries = attempts(work)

    def root_cause(key):                        # the first failed task key leads back to
        for d in deps.get(key, []):
            if d in errors:
                return root_cause(d)
        return key

    jobs = []
    for job in batch.jobs:
        failed = [k for k in job_tasks[job.name] if k in errors]
        rec = {"name": job.name, "out": job.out, "status": "failed" if failed else "ok"}
        if failed:
            origin = root_cause(failed[0])
            rec["failed_task"] = origin
            rec["error"] = errors.get(origin, errors[failed[0]])
        rec["renders"] = [_render_check(results[k]) for k in job_outs[job.name]
                          if k in results]
        jobs.append(rec)
    frames = [r for j in jobs for r in j["renders"]]
    return {
        "jobs_file": batch.path, "work": str(work), "seconds": round(seconds, 2),
        "jobs_ok": sum(j["status"] == "ok" for j in jobs),
        "jobs_failed": sum(j["status"] == "failed" for j in jobs),
        "tasks": len(refs), "tasks_failed": len(errors),
        "retried_tasks": sum(1 for k in refs if tries.get(k, 1) > 1),
        "attempts": {k: tries.get(k, 0) for k in refs},
        "frames": sum(r["frames"] for r in frames),
        "frames_lost": sum(r["lost"] for r in frames),
        "frames_rendered_twice": _twice(work),
        "partial_files": sum(r["partial_files"] for r in frames),
        "jobs": jobs,
        "task_results": results, "task_errors": errors,
    }


def _render_check(merge: dict) -> dict:
    """A finished render: its frames, how many PNGs are missing, temporaries left."""
    out = Path(merge["renders"])
    names = merge["frame_names"]
    return {"renders": str(out), "variant": merge["variant"], "frames": len(names),
            "lost": sum(not (out / f"{n}.png").is_file() for n in names),
            "partial_files": len(list(out.glob("*.tmp"))),
            **{k: merge[k] for k in ("psnr", "ssim", "video") if k in merge}}


def _twice(work) -> int:
    root = Path(work) / "records"
    return sum(len(list(d.iterdir())) for d in root.glob("*.twice")) if root.is_dir() else 0


def render_sharded(comp_dir, render: Render, address: str | None = None,
                   num_cpus: int | None = None, mi_variant: str = "auto", retries: int = 3,
                   work=None, task_cpus: int = 1) -> dict:
    """``comgs render-comp --ray``: ``render`` in ``render.shards`` tasks (None: one per CPU
    of the cluster, at most one per frame) and a merge; returns the merge's summary (plus
    ``shards``, ``attempts`` {task: attempts started}, ``lost``, ``partial_files``,
    ``frames_rendered_twice``, ``resumed_frames``: frames a retried shard found finished by
    its killed attempt). ``work`` None: ``COMP_DIR/.batch``."""
    import ray
    comp_dir = Path(comp_dir).resolve()             # workers may run elsewhere
    render = _absolute(render)
    work = Path(work).resolve() if work else comp_dir / ".batch"
    variant = render.settings.get("variant", "sop")
    label = f"render-comp-{variant}"
    shutil.rmtree(work / "attempts", ignore_errors=True)
    started = init_ray(address, num_cpus)
    try:
        if not render.shards:
            render.shards = max(1, int(ray.cluster_resources().get("CPU", 1) // task_cpus))
        sub, merge = _submit_render(str(comp_dir), render, label, work, mi_variant, task_cpus,
                                    retries, [])
        keys = dict(sub)
        try:
            s = ray.get(merge)
            parts = ray.get([r for k, r in sub if k != f"{label}.merge"])
        except Exception as e:                  # noqa: BLE001
            cause = getattr(e, "cause", None)
            if isinstance(cause, BaseException):
                raise cause from None
            raise RuntimeError("".join(traceback.format_exception_only(e)).strip()) from None
    finally:
        if started:
            ray.shutdown()
    tries = attempts(work)
    s.update(shards=render.shards, attempts={k: tries.get(k, 0) for k in keys},
             **{k: v for k, v in _render_check(s).items() if k in ("lost", "partial_files")},
             frames_rendered_twice=_twice(work),
             resumed_frames=sum(r["skipped"] for r in parts))
    return s


def _absolute(render: Render) -> Render:
    """``render`` with its files as absolute paths (a worker's folder is not ours)."""
    import dataclasses
    fix = (lambda v: None if v is None else str(Path(v).resolve()))
    settings = dict(render.settings)
    for k in ("video",) + (("path",) if str(settings.get("path")).endswith(".json") else ()):
        if settings.get(k) is not None:
            settings[k] = fix(settings[k])
    return dataclasses.replace(render, cameras=fix(render.cameras), gt_dir=fix(render.gt_dir),
                               settings=settings)
