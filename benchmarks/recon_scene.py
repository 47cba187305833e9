"""Scene preset of reconstruction step 1 on a small procedural scene (no masks, no download).

Generates a ground slab with four objects under the procedural sky (path traced, NeRF-synthetic
layout) with an SfM-like sparse cloud (``points3d.ply``: surface points seen by >= 2 training
views, coloured, jittered; what COLMAP gives a real capture), fits it with
`comgs reconstruct --scene` (init from those points, no mask loss, prune-only) and
prints the test PSNR/SSIM from `comgs render`. ``--points 0`` drops the cloud (random init).

    python benchmarks/recon_scene.py [--res 96] [--views 60] [--iterations 1500] [--points 20000]
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--points", type=int, default=20000, help="SfM-like points (0: none)")
    ap.add_argument("--init", default="auto", help="comgs reconstruct --init")
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "comgs_scene_bench")
    a = ap.parse_args()
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr import cli
    from comgs_dr.data.synthetic import make_object_dataset
    from comgs_dr.data.procedural import scene_dataset_config
    ds = a.out / "dataset"
    if (ds / "transforms_train.json").exists() and (ds / "points3d.ply").exists() != (a.points > 0):
        ap.error(f"{ds} was made with{'out' if a.points else ''} points; use another --out")
    if not (ds / "transforms_train.json").exists():
        make_object_dataset(scene_dataset_config(ds, a.views, 12, a.res, a.points), progress=False)
    run = a.out / "run"
    t0 = time.perf_counter()
    cli.main(["reconstruct", str(ds), "--out", str(run), "--scene", "--iterations", str(a.iterations),
              "--init", a.init, "--quiet"])
    t = time.perf_counter() - t0
    cli.main(["render", str(run), "--views", "test", "--quiet"])
    m = json.loads((run / "metrics_test.json").read_text())
    print(f"scene preset: {a.views} views at {a.res}px, {a.iterations} iterations in {t:.0f} s, "
          f"{m['surfels']} surfels: test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}")


if __name__ == "__main__":
    main()
