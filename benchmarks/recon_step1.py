"""Reconstruction step 1 benchmark: time per iteration by phase, and PSNR against wall time.

Phases of one iteration (object preset, hull init, at 100 px by default): bin (surfel frames,
projection, tile sort), walk (the per-pixel walks of the tile lists, every pass), composite
(forward compositing of the hit list), render (the whole ``mi.render``: the three above plus
rays and film), loss (L1 + SSIM + d2n + mask), backward (image adjoint + adjoint compositing
over the cached hit list), adam, update (parameters into the scene), python (what
``step()`` spends outside them: gradient guard, instruments, density strategy), and
``step()`` itself. Hit buffers side by side in one process (``--hits``).

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
          hits: tuple[int, int] = (128, 16), init: str = "auto") -> dict:
    """Median seconds per phase of a step-1 iteration (object preset, ``init``), after a
    few warm-up steps. The raster phases are timed by calling them directly on the
    iteration's own view: ``bin`` (surfel frames + projection + tile sort), ``walk`` (the
    per-pixel walks, every pass), ``composite`` (forward compositing of the hit list);
    ``render`` is the whole ``mi.render`` (the three above, rays and film), ``python`` what
    ``step()`` spends outside the measured phases."""
    import drjit as dr
    import mitsuba as mi

    from comgs_dr.data.load import load_dataset
    from comgs_dr.stages.reconstruct import RadianceConfig, Trainer
    from comgs_dr.surfels import composite, raster
    data = load_dataset(data_dir)
    cfg = RadianceConfig.from_preset("object", init=init, init_points=n_surfels,
                                     max_hits=hits[0], max_passes=hits[1])
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(data, tmp, cfg, progress=False)
        tr.integ.method = method
        for _ in range(3):
            tr.step()
        T = {k: [] for k in ("bin", "walk", "composite", "render", "loss", "backward", "adam",
                             "update", "step")}

        def tick(key, t0):
            dr.sync_thread()
            T[key].append(time.perf_counter() - t0)
        shapes = composite.surfel_shapes(tr.scene, "bench")
        for it in range(iters):
            i = it % len(tr.views)
            sensor = tr.scene.sensors()[i]
            if method == "raster":
                sampler, _ = tr.integ.prepare(sensor, it, 0, tr.integ.aov_names())
                ray, _, _ = tr.integ.sample_rays(tr.scene, sensor, sampler)
                pix = tr.integ._raster_ctx[1]
                t = time.perf_counter()
                view = raster.pinhole_view(sensor)
                geo = raster.surfel_geometry(shapes)
                lists = raster.bin_surfels(geo, view)
                tick("bin", t)
                t = time.perf_counter()
                hb, _ = raster.raster_all_hits(geo, lists, view, ray, pix, hits[0], True, hits[1])
                tick("walk", t)
                t = time.perf_counter()
                composite.composite_hits(shapes, ray, hb, tr.integ.targets)
                tick("composite", t)
            t = time.perf_counter(); img = mi.render(tr.scene, tr.mp, sensor=i, seed=it); dr.eval(img); tick("render", t)
            t = time.perf_counter(); total, _, _ = tr.loss(i, img); dr.eval(total); tick("loss", t)
            t = time.perf_counter(); dr.backward(total); dr.eval(dr.grad(tr.opt["surfels.means"])); tick("backward", t)
            t = time.perf_counter(); tr._guard_gradients(); tr.opt.step(); tr._clamp(); dr.eval(); tick("adam", t)
            t = time.perf_counter(); tr.mp.update(tr.opt); tick("update", t)
            t = time.perf_counter(); tr.step(); tick("step", t)
        med = {k: float(np.median(v)) if v else 0.0 for k, v in T.items()}
        med["python"] = max(med["step"] - sum(med[k] for k in ("render", "loss", "backward",
                                                                 "adam", "update")), 0.0)
        med["n"] = tr.params().count
        med["hits"] = float(np.mean(np.asarray(tr.integ._primal_cache[1][0].count)))
        return med


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="NeRF-synthetic folder (default: generated)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[100])
    ap.add_argument("--surfels", type=int, nargs="+", default=[20_000])
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--methods", nargs="+", default=["raster"])
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
        a.sizes, a.surfels, a.iters = [64], [5_000], 3
    root = Path(tempfile.gettempdir()) / "comgs_bench_recon"
    print(f"# machine: {platform.machine()}, {os.cpu_count()} cores | mitsuba {mitsuba.__version__}, "
          f"drjit {drjit.__version__}, llvm_ad_rgb | median ms per phase over {a.iters} "
          "iterations (object preset, hull init, after 3 warm-up steps)")
    cols = ("bin", "walk", "composite", "render", "loss", "backward", "adam", "update", "python")
    print(f"{'px':>4} {'surfels':>8} {'method':>7} {'hits':>7} " + " ".join(f"{c:>9}" for c in cols)
          + f" {'step()':>8} {'ratio':>6} {'hits/px':>7}")
    for res in a.sizes:
        data = a.data or make_data(res, root)
        for n in a.surfels:
            first = None
            for m in a.methods:
                for h in a.hits:
                    k, p = (int(v) for v in h.split("x"))
                    r = bench(data, n, a.iters, m, (k, p))
                    first = first or r["step"]
                    print(f"{res:>4} {r['n']:>8} {m:>7} {h:>7} "
                          + " ".join(f"{1000 * r[c]:>9.1f}" for c in cols)
                          + f" {1000 * r['step']:>8.1f} {r['step'] / first:>5.2f}x {r['hits']:>7.1f}")


if __name__ == "__main__":
    main()
