"""The command line: ``comgs batch JOBS.yaml [--ray ADDRESS]``, and ``--ray`` / ``--shards``
on ``comgs render-comp`` (docs/batch.md).

``add_render_comp_ray`` is called by ``cli.composition`` when it builds the render-comp
parser: it adds the Ray flags, with which the command runs sharded (``--ray``), and exactly
as before otherwise.
"""
from __future__ import annotations

import sys

from comgs_dr.cli._flags import field_overrides

RAY_HELP = ("Ray cluster to run on: 'local' (a local instance, as without the flag for "
            "batch), 'auto' (the cluster `ray start` made on this machine) or ADDRESS "
            "(host:port of its head, or ray://host:10001)")


def _add_batch(sub) -> None:
    p = sub.add_parser(
        "batch", help="run a jobs file (reconstruct, decompose, compose, render-comp) on Ray",
        description="Run the jobs of JOBS.yaml (docs/batch.md) as a Ray task graph: every "
                    "scene and object reconstructed once (objects then decomposed), every "
                    "composition and every frame shard of its renders a task of its own, "
                    "outputs in the folders the single commands write. A job that fails "
                    "(bad input) fails alone; a task whose worker dies is retried. Without "
                    "--ray a local Ray instance runs it. Writes WORK/summary.json (default "
                    "WORK: JOBS.batch/ beside the file); exit 0 when every job finished, 1 "
                    "when one failed, 2 for a jobs file that cannot run.")
    p.add_argument("jobs", metavar="JOBS.yaml")
    p.add_argument("--ray", metavar="ADDRESS", default=None, help=RAY_HELP)
    p.add_argument("--num-cpus", type=int, metavar="N", default=None,
                   help="CPUs of a local Ray instance (default: every core)")
    p.add_argument("--work", metavar="DIR", default=None,
                   help="attempt records, shard records, summary.json (default JOBS.batch/; "
                        "on a cluster a shared path)")
    p.add_argument("--quiet", action="store_true", help="only the summary")
    p.set_defaults(func=_cmd_batch)


def _cmd_batch(args) -> int:
    from comgs_dr.batch import load_jobs, run_batch
    batch = load_jobs(args.jobs)            # JobsFileError (a ValueError): exit 2
    if args.num_cpus is not None and args.num_cpus < 1:
        raise ValueError(f"--num-cpus must be >= 1, got {args.num_cpus}")
    s = run_batch(batch, args.ray, args.num_cpus, args.work,
                  say=(lambda *a: None) if args.quiet else print)
    for j in s["jobs"]:
        if j["status"] == "ok":
            frames = sum(r["frames"] for r in j["renders"])
            print(f"{j['name']}: ok -> {j['out']}" + (f" ({frames} frames)" if frames else ""))
        else:
            print(f"{j['name']}: FAILED in {j['failed_task']}: {j['error']}")
    print(f"batch: {s['jobs_ok']} of {len(s['jobs'])} jobs ok in {s['seconds']:.1f} s, "
          f"{s['tasks']} tasks ({s['retried_tasks']} retried), {s['frames']} frames "
          f"({s['frames_lost']} lost); summary {s['work']}/summary.json")
    return 0 if s["jobs_failed"] == 0 else 1


# ----------------------------------------------------------------------------- render-comp --ray

def add_render_comp_ray(p) -> None:
    """The Ray flags on the render-comp parser ``p`` (its command then dispatches on --ray)."""
    g = p.add_argument_group("Ray: the frames split over workers (docs/batch.md); the PNGs "
                             "are the single process's, byte for byte")
    g.add_argument("--ray", metavar="ADDRESS", default=None, help=RAY_HELP)
    g.add_argument("--shards", type=int, metavar="N", default=None,
                   help="frame shards, each a task (default: the cluster's CPUs)")
    g.add_argument("--num-cpus", type=int, metavar="N", default=None,
                   help="CPUs of a local Ray instance (--ray local; default: every core)")
    single = p.get_default("func")
    p.set_defaults(func=lambda args: _cmd_render_comp_ray(args) if args.ray else
                   _single(args, single))


def _single(args, single) -> int:
    if args.shards is not None or args.num_cpus is not None:
        raise ValueError("render-comp: --shards and --num-cpus split the frames over Ray "
                         "workers: give --ray too (local, auto or an address)")
    return single(args)


def _cmd_render_comp_ray(args) -> int:
    from comgs_dr.batch import render_sharded
    from comgs_dr.batch.spec import Render
    from comgs_dr.cli.composition import _materials
    from comgs_dr.stages.render_comp import RenderCompConfig, summary_line
    kw = field_overrides(args, RenderCompConfig)
    if "res" in kw and len(kw["res"]) == 1:          # --res W: a square W×W image
        kw["res"] = kw["res"][0]
    elif "res" in kw:
        kw["res"] = tuple(kw["res"])
    cfg = RenderCompConfig(materials=_materials(args.material), **kw)
    cfg.validate()
    if args.cameras is None and cfg.path is None:
        raise ValueError("render-comp: give --cameras (a transforms.json or a dataset "
                         "folder) or --path orbit|spiral|FILE")
    for flag, v in (("--shards", args.shards), ("--num-cpus", args.num_cpus)):
        if v is not None and v < 1:
            raise ValueError(f"render-comp: {flag} must be >= 1, got {v}")
    settings = {k: getattr(cfg, k) for k in ("variant", "materials", "res", "rays", "seed",
                                             "path", "frames", "video", "fps")}
    render = Render(args.cameras, args.gt_dir, args.shards, settings)
    s = render_sharded(args.comp_dir, render, args.ray, args.num_cpus, args.mitsuba_variant)
    retried = sum(n > 1 for n in s["attempts"].values())
    print(summary_line(s))
    print(f"ray: {s['shards']} shard(s), {retried} task(s) retried, {s['lost']} frame(s) "
          f"lost", file=sys.stderr if args.quiet else sys.stdout)
    return 0
