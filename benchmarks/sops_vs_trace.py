"""Step 2 with Surface Octahedral Probes vs per-iteration ray tracing, side by side.

For each setting (probe count × rays per shading point) both visibility sources train the
same step-1 geometry for the same number of iterations; the table gives the median
per-iteration split (shading-point materials / shading forward / backward / optimiser
step), the speed-up of SOPs, the test PBR PSNR, and relighting + albedo PSNR under the
dataset's held-out maps (``comgs relight``'s metrics). A second table gives test PSNR
against training time (error against run time).

    python benchmarks/sops_vs_trace.py --quick            # a few minutes: tiny dataset
    python benchmarks/sops_vs_trace.py --run RUN_DIR      # an existing step-1 run folder

Without ``--run`` a small object dataset is rendered (spot, held-out relight maps) and
surfels are sampled from the mesh as the step-1 geometry. The last line is
``speedup=<x> relight_psnr_gap_db=<y>`` (trace PSNR − SOP PSNR) for the last setting.
"""
from __future__ import annotations

import argparse
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_quick_run(root: Path, views: int, res: int, surfels: int) -> Path:
    """Tiny dataset + mesh-sampled surfels written as a step-1 run folder."""
    import trimesh

    from comgs_dr.data.synthetic import (
        ObjectDatasetConfig,
        make_object_dataset,
    )
    from comgs_dr.surfels import from_mesh, save_ply
    from comgs_dr.train.run import write_run_info
    ds = root / "data"
    make_object_dataset(ObjectDatasetConfig(out_dir=ds, n_train=views, n_test=6, resolution=res,
                                            spp=16, spp_aov=4), progress=False)
    meta = json.loads((ds / "meta.json").read_text())
    tm = trimesh.load(meta["mesh"], force="mesh")
    tm.apply_transform(np.asarray(meta["object"]["object_to_world"]))
    params = from_mesh(tm, surfels, seed=0, texture=meta.get("texture"))
    run = root / "run"
    write_run_info(run, ds, "object", 1, False)
    save_ply(params, str(run / "point_cloud.ply"))
    return run


def heldout_maps(run: Path) -> list[str]:
    info = json.loads((run / "run.json").read_text())
    meta = Path(info["data"]) / "meta.json"
    if not meta.exists():
        return []
    return list(json.loads(meta.read_text()).get("relight_envmaps", {}).values())


def train(run: Path, out: Path, visibility: str, probes: int, rays: int, iterations: int,
          env_res: int, eval_every: int) -> dict:
    from comgs_dr.stages.decompose import MaterialConfig, train_material
    from comgs_dr.stages.relight import relight_run
    cfg = MaterialConfig(visibility=visibility, probe_count=probes, rays=rays,
                         iterations=iterations, env_res=env_res, eval_every=eval_every,
                         eval_views=4, log_every=1, checkpoint_every=10 ** 9)
    t0 = time.perf_counter()
    s = train_material(run, out, cfg, progress=False)
    s["wall_s"] = time.perf_counter() - t0
    log = json.loads((out / "train_log.json").read_text())["log"]
    s["curve"] = [(r["time_s"], r["psnr_test"]) for r in log if "psnr_test" in r]
    rel = []
    for m in heldout_maps(run):
        r = relight_run(run, m, out, views="test", rays=rays, progress=False, max_views=6,
                        out_dir=out / f"relight_{Path(m).stem}")
        rel.append(r)
    s["relight_psnr"] = float(np.mean([r["relight_psnr"] for r in rel if "relight_psnr" in r])) \
        if rel and any("relight_psnr" in r for r in rel) else float("nan")
    s["albedo_psnr"] = float(np.mean([r["albedo_psnr"] for r in rel if "albedo_psnr" in r])) \
        if rel and any("albedo_psnr" in r for r in rel) else float("nan")
    return s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, help="step-1 run folder (default: a tiny built one)")
    ap.add_argument("--quick", action="store_true", help="one small setting, a few minutes")
    ap.add_argument("--iterations", type=int)
    ap.add_argument("--keep", type=Path, help="keep outputs in this folder")
    args = ap.parse_args(argv)
    import comgs_dr
    variant = comgs_dr.set_variant("auto")
    if args.quick:
        settings, its, env_res, views, res, n_surf = [(1000, 64)], 20, 64, 24, 64, 6000
    else:
        settings = [(1000, 32), (1000, 128), (5000, 32), (5000, 128)]
        its, env_res, views, res, n_surf = 60, 256, 60, 128, 20000
    its = args.iterations or its
    root = args.keep or Path(tempfile.mkdtemp(prefix="sops_bench_"))
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    run = args.run or make_quick_run(root, views, res, n_surf)
    print(f"# sops_vs_trace: {platform.machine()} {platform.processor() or ''}, variant "
          f"{variant}, run {run}, {its} iterations per row; setup {time.perf_counter() - t0:.0f} s")
    rows = []
    for probes, rays in settings:
        res_ = {}
        for vis in ("sops", "trace"):
            out = root / f"{vis}_{probes}_{rays}"
            if out.exists():
                shutil.rmtree(out)
            res_[vis] = train(run, out, vis, probes, rays, its, env_res, max(its // 4, 1))
        rows.append((probes, rays, res_))
        sp, tr = res_["sops"], res_["trace"]
        tot = lambda s: sum(s["median_step_split_s"].values())
        print(f"  done {probes} probes, {rays} rays: sops {tot(sp):.3f} s/it, trace "
              f"{tot(tr):.3f} s/it", flush=True)
    print()
    hdr = ("| probes | rays | source | render s | backward s | step s | s/it | speed-up "
           "| test PSNR | relight PSNR | albedo PSNR | setup (place+bake) s |")
    print(hdr)
    print("|" + "---|" * 12)
    for probes, rays, r in rows:
        t_tr = sum(r["trace"]["median_step_split_s"].values())
        for vis in ("sops", "trace"):
            s = r[vis]
            sp = s["median_step_split_s"]
            tot = sum(sp.values())
            st = s["setup_timings_s"]
            setup = st.get("placement_s", 0) + st.get("bake_s", 0)
            print(f"| {probes} | {rays} | {vis} | {sp['t_render']:.3f} | "
                  f"{sp['t_backward']:.3f} | {sp['t_step']:.3f} | {tot:.3f} | "
                  f"{t_tr / tot:.2f}x | {s['psnr_test']:.2f} | {s['relight_psnr']:.2f} | "
                  f"{s['albedo_psnr']:.2f} | {setup:.1f} |")
    print("\nerror against run time (test PBR PSNR at training time t):")
    for probes, rays, r in rows:
        for vis in ("sops", "trace"):
            pts = ", ".join(f"{t:.0f}s:{p:.2f}" for t, p in r[vis]["curve"])
            print(f"  {probes} probes {rays} rays {vis:5s}: {pts}")
    probes, rays, r = rows[-1]
    speed = sum(r["trace"]["median_step_split_s"].values()) / sum(
        r["sops"]["median_step_split_s"].values())
    gap = r["trace"]["relight_psnr"] - r["sops"]["relight_psnr"]
    if not args.keep and not args.run:
        shutil.rmtree(root, ignore_errors=True)
    print(f"speedup={speed:.2f} relight_psnr_gap_db={gap:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
