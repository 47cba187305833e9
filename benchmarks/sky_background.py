"""Step 1 with and without the learned sky (``RadianceConfig(background=...)``), end to end
to the lighting at a placement.

The capture is the demo's scene (``make-dataset composition``: gravel ground, brick wall,
box) under the procedural sky with a 25° sun, exposed for the sky (×0.6), seen by ``--views``
cameras looking down at it plus ``--sky-views`` from eye height looking out over the horizon.
For each background mode the scene is reconstructed (``--iters`` iterations), scored on the
held-out test views and on the sky views, and ``estimate_light`` runs at the placement of the
demo's object; the table reports the dominant light's angle to the true sun, the estimate's
total power and E(sun)/E(up) against the true map's.

    python benchmarks/sky_background.py [--out DIR] [--res 64] [--iters 800]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="out/sky_background")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--sky-views", type=int, default=12)
    ap.add_argument("--iters", type=int, default=800)
    ap.add_argument("--modes", default="grey,env")
    args = ap.parse_args()

    from comgs_dr import set_variant
    set_variant("auto")
    import mitsuba as mi

    from comgs_dr.data import procedural
    from comgs_dr.data.composition_dataset import CompositionDatasetConfig, make_composition_dataset
    from comgs_dr.data.load import load_dataset
    from comgs_dr.demo import OBJECT_MATERIAL
    from comgs_dr.eval import lighting_metrics
    from comgs_dr.eval.metrics import psnr
    from comgs_dr.lighting import backends, envmap
    from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light
    from comgs_dr.stages.reconstruct import RadianceConfig, train_radiance
    from comgs_dr.surfels import load_ply
    from comgs_dr.surfels.scene import gbuffer_scene
    from comgs_dr.emitters.octenvmap import emitter_class
    from comgs_dr.train import background as bgenv

    out = Path(args.out)
    (out / "inputs").mkdir(parents=True, exist_ok=True)
    ds = out / "dataset"
    if not (ds / "composition.json").exists():
        mesh = procedural.procedural_object_yup(out / "inputs" / "torus.ply")
        sky = procedural.procedural_sky(out / "inputs" / "sky.exr", sun_elevation_deg=25.0)
        studio = procedural.procedural_studio(out / "inputs" / "studio.exr")
        make_composition_dataset(CompositionDatasetConfig(
            out_dir=ds, objects=(str(mesh),), scene_map=sky, object_map=studio,
            resolution=args.res, scene_views=args.views, sky_views=args.sky_views,
            sky_pitch_deg=(10.0, 40.0), object_views=4, test_views=4, spp=32,
            sfm_points=5000, seed=0, path_material=OBJECT_MATERIAL, scene_envmap_scale=0.6),
            progress=False)
    meta = json.loads((ds / "composition.json").read_text())
    true_eq = envmap.read_envmap_file(meta["scene"]["envmap"])[0] * meta["scene"]["envmap_scale"]
    box = np.asarray(next(iter(meta["objects"].values()))["bbox_world"], np.float64)
    pos = box.mean(0)                                          # the object's centre
    data = load_dataset(ds / "scene")
    sky_views = data.train[-args.sky_views:] if args.sky_views else []
    backend = backends.load_network_backend()
    rows = []
    for mode in args.modes.split(","):
        run = out / f"scene_{mode}"
        t = time.perf_counter()
        s = train_radiance(data, run, RadianceConfig.from_preset(
            "scene", iterations=args.iters, eval_every=max(args.iters // 4, 1), eval_views=4,
            background=mode, env_resolution=128), progress=False)
        secs = time.perf_counter() - t
        p = load_ply(run / "point_cloud.ply")
        bg = bgenv.load(run)
        extra = dict(environment=emitter_class().from_radiance(bg[0]), env_background=True) \
            if bg is not None else {}
        sky_psnr = []
        for v in sky_views:
            sc = gbuffer_scene(p, v.camera.sensor_dict(), max_hits=24, targets="color", **extra)
            img = sc.integrator().split(mi.render(sc))["color"]
            sky_psnr.append(psnr(np.asarray(img), v.image))
        r = estimate_light(str(run / "point_cloud.ply"), pos, EstimateConfig(label="outdoor"),
                           backend)
        err = lighting_metrics.compare_maps(r["hdr"], true_eq)
        rows.append((mode, s["psnr_test"], float(np.mean(sky_psnr)) if sky_psnr else float("nan"),
                     secs, r["coverage"], err["light_angle_deg"], err["power_ratio_est_gt"],
                     err["light_up_irradiance_ratio_est"], err["light_up_irradiance_ratio_gt"]))
        print(f"[{mode}] done in {secs:.0f} s", flush=True)

    print(f"\nmachine: {platform.machine()}, {os.cpu_count()} cores; {args.views} + "
          f"{args.sky_views} sky views at {args.res} px, {args.iters} its\n")
    print("| background | test PSNR dB | sky views PSNR dB | train s | coverage at placement "
          "| light angle ° | power est/true | E(sun)/E(up) est (true) |")
    print("|---|---|---|---|---|---|---|---|")
    for m, pt, ps, secs, cov, ang, pw, re, rt in rows:
        print(f"| {m} | {pt:.2f} | {ps:.2f} | {secs:.0f} | {100 * cov:.1f} % | {ang:.1f} | "
              f"{pw:.2f} | {re:.2f} ({rt:.2f}) |")


if __name__ == "__main__":
    main()
