"""G-buffer benchmark: forward, forward+backward and BVH update of `surfel_gbuffer`.

Prints one table row per (surfel count, target set) with median times over
repeats, the ratio of a reduced target set to all targets, and the process's
peak resident memory. Each configuration runs in its own subprocess so peaks
and JIT caches do not leak between rows. Compile time (first call) is reported
separately from steady-state times.

    python benchmarks/gbuffer.py                 # 10k and 100k surfels, 256² rays, K=32
    python benchmarks/gbuffer.py --quick         # 10k surfels, 128² rays
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

from comgs_dr.surfels.scene import gbuffer_scene


def run_one(n: int, res: int, K: int, targets: str, repeats: int) -> dict:
    import resource

    import numpy as np
    import trimesh

    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    import drjit as dr
    import mitsuba as mi

    from comgs_dr.core import cameras
    from comgs_dr.surfels import from_mesh

    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    mesh = trimesh.util.concatenate([mesh, trimesh.creation.box((2.5, 2.5, 0.1), transform=trimesh.transformations.translation_matrix([0, 0, -0.9]))])
    params = from_mesh(mesh, n, seed=0)
    scene = gbuffer_scene({"obj": params}, cameras.perspective([0, -3.2, 1.6], res=res, fov=45),
                                  max_hits=K, targets=targets)
    mp = mi.traverse(scene)

    def timed(fn):
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0

    def fwd():
        dr.eval(mi.render(scene, spp=1))
        dr.sync_thread()

    keys = ["obj.means", "obj.quats", "obj.log_scales", "obj.opacity_logit", "obj.sh"]

    def fwd_bwd():
        for k in keys:
            dr.enable_grad(mp[k])
        img = mi.render(scene, mp, spp=1)
        dr.backward(dr.sum(img, axis=None))
        dr.eval([dr.grad(mp[k]) for k in keys])
        dr.sync_thread()
        for k in keys:
            dr.disable_grad(mp[k])

    means0 = mi.Point3f(mp["obj.means"])

    def bvh():
        mp["obj.means"] = means0 + mi.Vector3f(1e-4, 0, 0)
        mp.update()
        dr.sync_thread()

    first_fwd, first_bwd = timed(fwd), timed(fwd_bwd)
    t_fwd = sorted(timed(fwd) for _ in range(repeats))[repeats // 2]
    t_bwd = sorted(timed(fwd_bwd) for _ in range(repeats))[repeats // 2]
    t_bvh = sorted(timed(bvh) for _ in range(repeats))[repeats // 2]
    img = np.array(mi.render(scene))
    return {"n": n, "res": res, "K": K, "targets": targets, "first_fwd": first_fwd,
            "first_fwd_bwd": first_bwd, "fwd": t_fwd, "fwd_bwd": t_bwd, "bvh_update": t_bvh,
            "coverage": float((img[..., 3] > 0.5).mean()) if img.shape[2] > 3 else float("nan"),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--K", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="10k surfels, 128² rays")
    ap.add_argument("--_one", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a._one:
        n, res, K, targets, rep = json.loads(a._one)
        print(json.dumps(run_one(n, res, K, targets, rep)))
        return
    if a.quick:
        a.sizes, a.res = [10_000], 128
    import drjit
    import mitsuba
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"{platform.system()} | mitsuba {mitsuba.__version__}, drjit {drjit.__version__}, llvm_ad_rgb")
    print(f"# rays: {a.res}x{a.res} (1 spp), K={a.K}, median of {a.repeats}; fwd+bwd = render + "
          "backward to means/quats/scales/opacity/SH; 'first' includes JIT compilation")
    hdr = (f"{'surfels':>8} {'targets':<22} {'first fwd':>9} {'fwd s':>7} {'first f+b':>9} "
           f"{'f+b s':>7} {'bvh s':>7} {'f+b/fwd':>7} {'vs all':>7} {'peak MB':>8}")
    print(hdr)
    print("-" * len(hdr))
    for n in a.sizes:
        base = None
        for targets in ("all", "color,weight,depth_unbiased,normal"):
            out = subprocess.run([sys.executable, __file__, "--_one", json.dumps([n, a.res, a.K, targets, a.repeats])],
                                 capture_output=True, text=True)
            if out.returncode != 0:
                print(f"{n:>8} {targets:<22} FAILED: {out.stderr.strip().splitlines()[-1]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            base = base or r["fwd_bwd"]
            print(f"{n:>8} {targets[:22]:<22} {r['first_fwd']:>9.2f} {r['fwd']:>7.3f} {r['first_fwd_bwd']:>9.2f} "
                  f"{r['fwd_bwd']:>7.3f} {r['bvh_update']:>7.3f} {r['fwd_bwd'] / r['fwd']:>7.2f} "
                  f"{r['fwd_bwd'] / base:>7.2f} {r['peak_rss_mb']:>8.0f}")


if __name__ == "__main__":
    main()
