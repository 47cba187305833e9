"""Run time of the lighting-estimation stage (trace + 3 EV completions + fusion + octahedral).

Builds a procedural surfel room (``pano_data``'s mask scenes, ``from_mesh``) at a few surfel
counts, runs ``estimate_light`` at the placement with the shipped network and with the
push-pull fill, and prints the time split. The issue's target is ≤ 30 s for trace + 3 EV
passes + fusion on 2 cores at 1024×512.

    python benchmarks/estimate_light.py [--surfels 20000 200000] [--width 1024]
"""
from __future__ import annotations

import argparse
import os
import platform
import time


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--surfels", type=int, nargs="+", default=[20000, 200000])
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=3)
    a = ap.parse_args(argv)
    import numpy as np

    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.data.pano_masks import random_surfel_scene
    from comgs_dr.lighting import backends
    from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light
    from comgs_dr.surfels.scene import gbuffer_scene
    methods = {"net": backends.load_network_backend(), "push_pull": backends.FillBackend("push_pull")}
    cfg = EstimateConfig(width=a.width // 2 * 2, height=a.width // 2, exclude_radius=0.1)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}; trace {a.width}x{a.width // 2}, K={cfg.max_hits}\n")
    cols = ("trace", "completion", "fusion", "octahedral", "lights", "total")
    print("| surfels | backend | coverage | " + " | ".join(f"{c} s" for c in cols)
          + " | trace+3 EV+fusion s |")
    print("|---|---|---|" + "---|" * (len(cols) + 1))
    for n in a.surfels:
        rng = np.random.default_rng(a.seed)
        while True:   # a room (the generator alternates rooms and yards)
            params, (lo, hi) = random_surfel_scene(rng, n)
            if lo[2] > 0.25:
                break
        scene = gbuffer_scene(params, [], targets="weight")
        pos = (lo + hi) / 2
        estimate_light(scene, pos, EstimateConfig(width=64, height=32, oct_res=16),
                       methods["push_pull"])                          # warm the kernels
        for name, be in methods.items():
            t0 = time.perf_counter()
            r = estimate_light(scene, pos, cfg, be)
            wall = time.perf_counter() - t0
            t = r["timings"]
            core = t["trace"] + t["completion"] + t["fusion"]
            print(f"| {n} | {name} | {100 * r['coverage']:.0f} % | "
                  + " | ".join(f"{t.get(c, wall if c == 'total' else float('nan')):.2f}"
                               for c in cols) + f" | {core:.2f} |")


if __name__ == "__main__":
    main()
