"""Relighting estimators against a path-traced reference, error against run time.

The object's true geometry and material are given to both estimators (surfels sampled
from the mesh with the dataset's base colour and roughness, occlusion traced), so the
table isolates the rendering estimator from reconstruction (default ``--visibility none``:
traced self-occlusion without the indirect term shows shadow acne that would dominate): the old one (the paper's
uniform hemisphere with one rotated Hammersley set shared by all pixels, the map resampled
to 256²) against the new default (``sop_pbr``'s MIS of env-map and BRDF sampling, one set
per pixel, the map at full resolution), over several ray counts S_r, under a held-out map
with a sun. PSNR is on display sRGB against ``comgs make-dataset object``'s path-traced
``test_relight`` images (composited over black as ``comgs relight`` does).

    python benchmarks/relight_estimators.py                       # teapot, venice_sunset
    python benchmarks/relight_estimators.py --quick               # 64 px, 3 views
    python benchmarks/relight_estimators.py --map kiara_1_dawn_1k.hdr --mesh suzanne.obj
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data-dir", default=os.environ.get("COMGS_DATA_DIR", "../shared/data"))
    ap.add_argument("--mesh", default="teapot.obj")
    ap.add_argument("--map", default="venice_sunset_1k.hdr", help="held-out relighting map (sun)")
    ap.add_argument("--train-map", default="blender_studio.exr")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--rays", type=int, nargs="+", default=[32, 64, 128, 256, 512])
    ap.add_argument("--surfels", type=int, default=60000)
    ap.add_argument("--visibility", default="none", choices=("none", "trace"),
                    help="occlusion of the true geometry (trace: rays through the surfels)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--keep", type=Path)
    args = ap.parse_args(argv)
    if args.quick:
        args.res, args.views, args.rays, args.surfels = 64, 3, [16, 64], 15000
    import drjit as dr
    import mitsuba as mi
    import trimesh

    import comgs_dr
    from comgs_dr.core.colorspace import display_composite, srgb_encode
    from comgs_dr.core.exr import read_image
    from comgs_dr.data.synthetic import ObjectDatasetConfig, make_object_dataset
    from comgs_dr.eval.metrics import psnr
    from comgs_dr.surfels import from_mesh
    from comgs_dr.surfels.shape import SurfelShapeBase
    variant = comgs_dr.set_variant("auto")
    data = Path(args.data_dir)
    root = args.keep or Path(tempfile.mkdtemp(prefix="relight_est_"))
    ds = root / "data"
    base_color, rough = (0.70, 0.35, 0.18), 0.45
    t0 = time.perf_counter()
    if not (ds / "meta.json").exists():
        make_object_dataset(ObjectDatasetConfig(
            mesh=data / "meshes" / args.mesh, envmap=data / "hdri" / args.train_map, out_dir=ds,
            n_train=1, n_test=args.views, resolution=args.res, spp=16, spp_test=256, spp_aov=4,
            relight_envmaps=(str(data / "hdri" / args.map),), texture=None, base_color=base_color,
            roughness=rough), progress=True)
    meta = json.loads((ds / "meta.json").read_text())
    tm = trimesh.load(data / "meshes" / args.mesh, force="mesh")
    tm.apply_transform(np.asarray(meta["object"]["object_to_world"]))
    params = from_mesh(tm, args.surfels, seed=0, opacity=0.99, roughness=rough)
    d = params.to_numpy()
    d["albedo"][:] = base_color
    params = type(params).from_numpy(**d)
    frames = json.loads((ds / "transforms_test.json").read_text())["frames"]
    stem = Path(args.map).stem
    gts, sensors = [], []
    from comgs_dr.data.load import load_dataset
    dset = load_dataset(ds)
    for v in dset.test[:args.views]:
        gt = read_image(ds / "test_relight" / stem / f"{Path(v.name).name}.exr").astype(np.float64)
        a = gt[..., 3:4]
        gts.append(a * srgb_encode(np.clip(gt[..., :3] / np.maximum(a, 1e-6), 0, 1)))
        sd = v.camera.sensor_dict()
        sensors.append({**sd, "film": {**sd["film"], "pixel_format": "rgba"}})
    print(f"# relight_estimators: {platform.machine()}, {variant}, {args.mesh} under {args.map}, "
          f"{args.views} views at {args.res}², {params.count} surfels with the true material, "
          f"visibility {args.visibility}; setup {time.perf_counter() - t0:.0f} s")
    variants = {
        "old: uniform, shared set, map 256²": dict(sampling="uniform", decorrelate=False, res=256),
        "new: MIS, per-pixel sets, full map": dict(sampling="mis", decorrelate=True, res=None),
    }
    print("| estimator | S_r | s/view | PSNR (dB) |")
    print("|---|---|---|---|")
    results = {}
    for name, v in variants.items():
        em = {"type": "octenvmap", "filename": str(data / "hdri" / args.map)}
        if v["res"]:
            em["resolution"] = v["res"]
        for S in args.rays:
            scene_d = {"type": "scene", "obj": SurfelShapeBase.from_params(params, id="obj"),
                       "env": em, "integrator": {"type": "sop_pbr", "visibility": args.visibility,
                                                 "rays": S, "sampling": v["sampling"],
                                                 "decorrelate": v["decorrelate"], "indirect": False,
                                                 "hide_emitters": True, "trace_hits": 16}}
            for i, sd in enumerate(sensors):
                scene_d[f"s{i:03d}"] = sd
            scene = mi.load_dict(scene_d)
            mi.render(scene, sensor=0, seed=0)               # warm-up: kernels + hit caches
            for i in range(len(sensors)):
                scene.integrator().shading_points(scene, i)
            ps, t1 = [], time.perf_counter()
            for i in range(len(sensors)):
                with dr.suspend_grad():
                    img = np.asarray(display_composite(mi.render(scene, sensor=i, seed=1 + i), 0.0))
                ps.append(psnr(np.clip(img, 0, 1), gts[i]))
            dt = (time.perf_counter() - t1) / len(sensors)
            results.setdefault(name, []).append((S, dt, float(np.mean(ps))))
            print(f"| {name} | {S} | {dt:.3f} | {np.mean(ps):.2f} |", flush=True)
    # equal time: the new estimator at its cheapest row vs the old one at the row whose time is closest
    new, old = results[list(variants)[1]], results[list(variants)[0]]
    print("\nequal time (old row with the nearest time to each new row):")
    for S, dt, p in new:
        j = int(np.argmin([abs(o[1] - dt) for o in old]))
        print(f"  new S_r={S} {dt:.3f} s: {p:.2f} dB | old S_r={old[j][0]} {old[j][1]:.3f} s: {old[j][2]:.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
