"""Composition benchmark: the paper's composition table on a generated set.

Runs the whole pipeline through the CLI (each step skipped when its output exists):
``make-dataset composition`` → ``reconstruct --scene`` on the scene → ``reconstruct
--object`` + ``decompose`` per object → ``compose`` (lighting: the scene's true map with
``--env-true``, else estimated) → ``render-comp`` for paste, noshadow, trace and sop against
the path-traced composites. Prints PSNR / SSIM / frame time per variant, trace/sop speed
ratio and the edit time (edit.json).

    python benchmarks/composition.py --work /tmp/compbench            # ~15-25 min on 2 cores
    python benchmarks/composition.py --work /tmp/compbench --known-object-light   # + step 2
                                                  # under each object's capture map
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

VARIANTS = ("paste", "noshadow", "trace", "sop")


def run(cmd, log):
    t = time.perf_counter()
    print("$ " + " ".join(map(str, cmd)), flush=True)
    r = subprocess.run([sys.executable, "-m", "comgs_dr.cli", *map(str, cmd)],
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log.write(r.stdout)
    if r.returncode:
        print(r.stdout[-3000:])
        raise SystemExit(f"failed ({r.returncode}): {' '.join(map(str, cmd))}")
    dt = time.perf_counter() - t
    print(f"  {dt:.0f} s: {r.stdout.strip().splitlines()[-1] if r.stdout.strip() else ''}",
          flush=True)
    return dt


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/compbench"))
    ap.add_argument("--objects", default="spot,teapot")
    ap.add_argument("--scene-map", default=None)
    ap.add_argument("--object-map", default=None,
                    help="map the objects are captured under (default: the dataset's studio)")
    ap.add_argument("--res", type=int, default=96, help="side of the captures")
    ap.add_argument("--comp-res", type=int, default=None,
                    help="side of the composites (default --res; e.g. --res 128 --comp-res 256)")
    ap.add_argument("--ground-tint", type=float, nargs=3, default=None,
                    help="sRGB multipliers of the ground's texture (default: the dataset's "
                         "warm grey; 1.25 1.25 1.2: a pale ground)")
    ap.add_argument("--sky-views", type=int, default=None,
                    help="scene views over the horizon (default: the dataset's, 0: none)")
    ap.add_argument("--test-views", type=int, default=8)
    ap.add_argument("--scene-iters", type=int, default=1500)
    ap.add_argument("--object-iters", type=int, default=1500)
    ap.add_argument("--decompose-iters", type=int, default=600)
    ap.add_argument("--shadow-probes", type=int, default=10000)
    ap.add_argument("--rays", type=int, default=256)
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help="render-comp variants to render (paste and sop always; trace is the "
                         "slow one: leave it out for a quick look)")
    ap.add_argument("--estimate", action="store_true",
                    help="estimate the lighting at each placement instead of the true map")
    ap.add_argument("--known-object-light", action="store_true",
                    help="step 2 of each object under its capture's own map (decompose "
                         "--env-file), in obj_<name>_known/")
    a = ap.parse_args(argv)
    variants = [v for v in VARIANTS if v in {"paste", "sop", *a.variants.split(",")}]
    w = a.work
    w.mkdir(parents=True, exist_ok=True)
    log = open(w / "log.txt", "a")
    ds = w / "data"
    times = {}
    if not (ds / "composition.json").is_file():
        cmd = ["make-dataset", "composition", "--out", ds, "--objects", a.objects, "--res", a.res,
               "--test-views", a.test_views, "--quiet"]
        if a.scene_map:
            cmd += ["--scene-map", a.scene_map]
        if a.object_map:
            cmd += ["--object-map", a.object_map]
        if a.comp_res:
            cmd += ["--comp-res", a.comp_res]
        if a.sky_views is not None:
            cmd += ["--sky-views", a.sky_views]
        if a.ground_tint is not None:
            cmd += ["--ground-tint", *a.ground_tint]
        times["dataset"] = run(cmd, log)
    meta = json.loads((ds / "composition.json").read_text())
    names = list(meta["objects"])
    if not (w / "scene_run" / "point_cloud.ply").is_file():
        times["scene step 1"] = run(["reconstruct", ds / "scene", "--out", w / "scene_run",
                                     "--scene", "--iterations", a.scene_iters, "--quiet"], log)
    objects = {}
    for n in names:
        r = w / f"obj_{n}"
        if not (r / "point_cloud.ply").is_file():
            times[f"{n} step 1"] = run(["reconstruct", ds / "objects" / n, "--out", r, "--object",
                                        "--iterations", a.object_iters, "--quiet"], log)
        cmd, mat = ["decompose", r, "--iterations", a.decompose_iters, "--quiet"], r
        if a.known_object_light:            # the object's own capture light, kept fixed
            om = json.loads((ds / "objects" / n / "meta.json").read_text())
            mat = w / f"obj_{n}_known"
            mat.mkdir(exist_ok=True)
            for f in r.iterdir():           # the step-1 state, without its material/
                if f.is_file() and not (mat / f.name).exists():
                    shutil.copy(f, mat / f.name)
            cmd = ["decompose", mat, "--iterations", a.decompose_iters, "--quiet",
                   "--env-file", om["envmap"], "--env-scale", om.get("envmap_scale", 1.0)]
        if not (mat / "material" / "probes.npz").is_file():
            times[f"{n} step 2"] = run(cmd, log)
        objects[n] = mat
    comp = w / (("comp_est" if a.estimate else "comp") + ("_known" if a.known_object_light else ""))
    cmd = ["compose", w / "scene_run", "--placement", ds / "transform.json", "--out", comp,
           "--shadow-probes", a.shadow_probes, "--quiet"]
    for n in names:
        cmd += ["--object", f"{n}={objects[n]}"]
    if not a.estimate:
        cmd += ["--env", meta["scene"]["envmap"]]
    times["compose"] = run(cmd, log)
    edit = json.loads((comp / "edit.json").read_text())
    rows = {}
    for v in variants:
        run(["render-comp", comp, "--cameras", ds / "comp" / "transforms_test.json",
             "--variant", v, "--gt-dir", ds / "comp" / "gt", "--rays", a.rays, "--quiet"], log)
        rows[v] = json.loads((comp / f"metrics_{v}.json").read_text())
    print(f"\ncomposition on {ds} ({len(names)} objects: {', '.join(names)}; "
          f"{rows['sop']['frames']} frames at {rows['sop']['resolution']})")
    print(f"{'variant':<10}{'PSNR':>8}{'SSIM':>8}{'s/frame':>10}{'FPS':>8}")
    for v in variants:
        r = rows[v]
        print(f"{v:<10}{r['psnr']:>8.2f}{r['ssim']:>8.4f}{r['frame_seconds']:>10.3f}"
              f"{1 / r['frame_seconds']:>8.2f}")
    if all("region" in rows[v] for v in variants):
        print(f"\nin the object+shadow region (eval.comp_region):\n{'variant':<10}{'PSNR':>8}"
              f"{'shadow':>8}{'truth':>8}{'depth':>7}{'area':>7}   object colour / truth")
        for v in variants:
            g = rows[v]["region"]
            col = ", ".join(f"{c:.2f}" for c in g.get("object_colour_ratio", []))
            print(f"{v:<10}{g['psnr_region']:>8.2f}{g.get('shadow_ratio', float('nan')):>8.3f}"
                  f"{g.get('shadow_ratio_truth', float('nan')):>8.3f}"
                  f"{g.get('shadow_depth', float('nan')):>7.2f}"
                  f"{g.get('shadow_depth_area', float('nan')):>7.2f}   {col}")
    if "trace" in rows:
        print(f"trace / sop frame time: "
              f"{rows['trace']['frame_seconds'] / rows['sop']['frame_seconds']:.2f}x;"
              f" sop - trace PSNR: {rows['sop']['psnr'] - rows['trace']['psnr']:+.2f} dB")
    t = edit["timings"]
    print(f"edit ({edit['probes']['shadow']} shadow probes, {edit['rays_per_probe']} rays each): "
          + ", ".join(f"{k} {t[k]:.1f} s" for k in ("lighting", "probe_placement",
                                                     "occlusion_tracing", "total")))
    per = [(f["name"], {v: rows[v]["per_frame"][i]["psnr"] for v in variants})
           for i, f in enumerate(rows["sop"]["per_frame"])]
    worse = [n for n, p in per if p["sop"] <= p["paste"]]
    print(f"sop better than paste on {len(per) - len(worse)}/{len(per)} frames"
          + (f" (not on {', '.join(worse)})" if worse else ""))
    print("pipeline step times: " + ", ".join(f"{k} {v:.0f} s" for k, v in times.items()))
    (w / "table.json").write_text(json.dumps({"variants": rows, "edit": edit,
                                              "times": times}, indent=1))


if __name__ == "__main__":
    main()
