"""Reconstruction step 1 benchmark: time per iteration by phase, and PSNR against wall time.

Phases: render (hit finding + forward compositing), loss (L1 + SSIM + d2n + mask), backward
(image adjoint + adjoint compositing over the cached hit buffer), adam, update (parameters
into the scene), density (one densify-and-prune, amortised over its interval), and
``step()``: a whole training step as the trainer runs it (random background included). Two image
sizes x two surfel counts x the two hit-finding methods of ``surfel_gbuffer``, side by side
in one process: ``trace`` (before: Embree, with the proxy/BVH rebuild that every traced
step needs, now inside "render") and ``raster`` (tile rasterisation; no BVH).

    python benchmarks/recon_step1.py [--data DIR] [--quick] [--hits 24x1 128x16]
    python benchmarks/recon_step1.py --run RUN_DIR     # PSNR-vs-time table of a finished run
    python benchmarks/recon_step1.py --compare NAME=RUN_DIR ...   # before/after table of runs

``--hits KxP`` compares hit buffers side by side: K slots per ray and P passes (24x1: the
first 24 hits only, what step 1 did before; 128x16: every surfel on the ray).
``--compare`` prints, per run: test PSNR best (iteration) and final, the largest fall below
the best so far after iteration 1000, surfels at the end, seconds per iteration, the mean
share of pixels whose compositing stopped early (hit buffer full while T > 1e-3, the last
500 iterations) and hits per pixel, and whether the best state was restored.

Without --data, a small procedural object dataset is generated (no download).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np


def psnr_table(run: Path) -> None:
    log = json.loads((run / "train_log.json").read_text())
    print(f"# {run}: test PSNR against training wall-clock time")
    print(f"{'iteration':>9} {'time s':>8} {'surfels':>8} {'test PSNR':>9}")
    for r in log["log"]:
        if "psnr_test" in r:
            print(f"{r['iteration']:>9} {r['time_s']:>8.1f} {r['surfels']:>8} {r['psnr_test']:>9.2f}")


def compare_table(runs: list[str]) -> None:
    print(f"{'run':<22} {'best dB':>8} {'@it':>5} {'final':>6} {'fall>1k':>7} {'surfels':>8} "
          f"{'s/it':>6} {'early':>6} {'hits/px':>7} restored")
    for spec in runs:
        name, _, path = spec.rpartition("=")
        f = Path(path) / "train_log.json"
        if f.exists():
            log = json.loads(f.read_text())
            recs, summ = log["log"], log.get("summary") or {}
        else:                                           # a run still going: its metrics.jsonl
            recs = [json.loads(x) for x in (Path(path) / "metrics.jsonl").read_text().splitlines()]
            summ = {}
        ev = [r for r in recs if "psnr_test" in r]
        if not ev:
            print(f"{name or path:<22} (no evaluation yet)")
            continue
        best = max(ev, key=lambda r: r["psnr_test"])
        fall, top = 0.0, -1e9
        for r in ev:
            top = max(top, r["psnr_test"])
            if r["iteration"] > 1000:
                fall = max(fall, top - r["psnr_test"])
        last = recs[-1]
        tail = [r for r in recs if r["iteration"] > last["iteration"] - 500]
        early = np.mean([r.get("open_frac", np.nan) for r in tail])
        hits = np.mean([r.get("hits_mean", np.nan) for r in tail])
        s_it = last["time_s"] / max(last["iteration"], 1)
        div = summ.get("diverged")
        restored = "-" if not div else str(div.get("restored", True))
        print(f"{name or path:<22} {best['psnr_test']:>8.2f} {best['iteration']:>5} "
              f"{ev[-1]['psnr_test']:>6.2f} {fall:>7.2f} {last.get('surfels', 0):>8} "
              f"{s_it:>6.3f} {early:>6.3f} {hits:>7.1f} {restored}")


def make_data(res: int, root: Path) -> Path:
    from comgs_dr.data.synthetic import ObjectDatasetConfig, make_object_dataset
    from comgs_dr.data.procedural import procedural_object, procedural_sky
    out = root / f"ds{res}"
    if not (out / "transforms_train.json").exists():
        root.mkdir(parents=True, exist_ok=True)
        make_object_dataset(ObjectDatasetConfig(
            mesh=procedural_object(root / "obj.ply"), envmap=procedural_sky(root / "sky.exr"), out_dir=out,
            n_train=20, n_test=4, resolution=res, spp=16, spp_aov=2, relight_envmaps=(), up_axis="z",
            texture=None), progress=False)
    return out


def bench(data_dir: Path, n_surfels: int, iters: int, method: str = "raster",
          hits: tuple[int, int] = (128, 16)) -> dict:
    import drjit as dr
    import mitsuba as mi

    from comgs_dr.data.load import load_dataset
    from comgs_dr.stages.reconstruct import PARAM_KEYS, RadianceConfig, Trainer
    data = load_dataset(data_dir)
    cfg = RadianceConfig(init="random", init_points=n_surfels, densify=dict(start=10 ** 9),
                         sh_increase_every=0, sh_degree=0, max_hits=hits[0], max_passes=hits[1])
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(data, tmp, cfg, progress=False)
        tr.integ.method = method
        T = {k: [] for k in ("render", "loss", "backward", "adam", "update", "density")}

        def tick(key, t0):
            dr.sync_thread()
            T[key].append(time.perf_counter() - t0)
        for it in range(iters + 2):
            i = it % len(tr.views)
            t = time.perf_counter(); img = mi.render(tr.scene, tr.mp, sensor=i, seed=it); dr.eval(img); tick("render", t)
            t = time.perf_counter(); total, _, _ = tr.loss(i, img); dr.eval(total); tick("loss", t)
            t = time.perf_counter(); dr.backward(total); dr.eval(dr.grad(tr.opt["surfels.means"])); tick("backward", t)
            t = time.perf_counter(); tr._guard_gradients(); tr.opt.step(); tr._clamp(); dr.eval(); tick("adam", t)
            t = time.perf_counter(); tr.mp.update(tr.opt); tick("update", t)
        # the training step itself (random background, SH/density schedule, logging values):
        # overheads outside the phases above show here (a background compiled into the
        # kernels as a literal once recompiled every step: 316 vs 106 ms at 100 px)
        steps = []
        for it in range(iters + 2):
            dr.sync_thread()
            t = time.perf_counter()
            tr.step()
            dr.sync_thread()
            steps.append(time.perf_counter() - t)
        t = time.perf_counter()
        tr.strategy.controller.accumulate(np.asarray(dr.grad(tr.opt["surfels.means"])).T + 1e-3,
                              np.asarray(tr.opt["surfels.means"]).T, np.zeros(3), 0.36)
        new, _ = tr.strategy.controller.densify_and_prune(tr.params(), tr.opt, dict(PARAM_KEYS), np.random.default_rng(0))
        tick("density", t)
        med = {k: float(np.median(v[2:] if len(v) > 2 else v)) for k, v in T.items()}
        med["density"] /= tr.strategy.controller.cfg.interval
        med["n"] = tr.params().count
        med["step"] = float(np.median(steps[2:]))
        med["hits"] = float(np.mean(np.asarray(tr.integ._primal_cache[1][0].count)))
        return med


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="NeRF-synthetic folder (default: generated)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--surfels", type=int, nargs="+", default=[10_000, 40_000])
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--methods", nargs="+", default=["trace", "raster"])
    ap.add_argument("--quick", action="store_true", help="64 px, 10k surfels, 5 iterations")
    ap.add_argument("--hits", nargs="+", default=["24x1", "128x16"],
                    help="hit buffers KxP to compare (K slots, P passes)")
    ap.add_argument("--run", type=Path, help="print the PSNR-vs-time table of a run and exit")
    ap.add_argument("--compare", nargs="+", metavar="NAME=RUN",
                    help="print the before/after table of finished runs and exit")
    a = ap.parse_args()
    if a.run:
        psnr_table(a.run)
        return
    if a.compare:
        compare_table(a.compare)
        return
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    import drjit
    import mitsuba
    if a.quick:
        a.sizes, a.surfels, a.iters = [64], [10_000], 5
    root = Path(tempfile.gettempdir()) / "comgs_bench_recon"
    print(f"# machine: {platform.machine()}, {os.cpu_count()} cores | mitsuba {mitsuba.__version__}, "
          f"drjit {drjit.__version__}, llvm_ad_rgb | median ms per iteration over {a.iters}")
    cols = ("render", "loss", "backward", "adam", "update", "density")
    print(f"{'px':>4} {'surfels':>8} {'method':>7} {'hits':>7} " + " ".join(f"{c:>8}" for c in cols)
          + f" {'total':>8} {'it/s':>6} {'ratio':>8} {'step()':>8} {'hits/px':>7}")
    for res in a.sizes:
        data = a.data or make_data(res, root)
        for n in a.surfels:
            first = None
            for m in a.methods:
                for h in a.hits:
                    k, p = (int(v) for v in h.split("x"))
                    r = bench(data, n, a.iters, m, (k, p))
                    tot = sum(r[c] for c in cols)
                    first = first or tot
                    print(f"{res:>4} {r['n']:>8} {m:>7} {h:>7} "
                          + " ".join(f"{1000 * r[c]:>8.1f}" for c in cols)
                          + f" {1000 * tot:>8.1f} {1 / tot:>6.2f} {tot / first:>7.2f}x "
                          f"{1000 * r['step']:>8.1f} {r['hits']:>7.1f}")


if __name__ == "__main__":
    main()
