"""The relit object's colour and noise in a composite, against the path-traced truth.

In the truth's object pixels (``comp/mask``) of a composition dataset: the mean linear
colour of each variant over the truth's, per channel (1: right; the paste shows the
object's captured colour, so its ratio says how far the capture's light is from the
scene's), and the per-pixel noise of the relit object: the standard deviation of the
difference of two renders with different seeds / √2, relative to the object's mean, at
several ray counts (``rays`` of ``comgs_composite``; 1/√rays if the estimator is the
source). Frame time per row.

    python benchmarks/object_colour.py --data /tmp/demo/dataset --comp /tmp/demo/comp
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def render(comp: Path, cams, variant: str, rays: int, seed: int, **extra):
    """{frame: linear RGB [H, W, 3]}."""
    import drjit as dr
    import mitsuba as mi

    from comgs_dr.data import comp_folder
    from comgs_dr.stages.render_comp import load_comp_scene
    manifest = comp_folder.read_manifest(comp)
    scene = load_comp_scene(comp, variant, None,
                            [comp_folder.sensor_dict(cams[0],
                                                     clip=comp_folder.clip_for(manifest, cams))],
                            rays=rays, shadow_rays=rays, **extra)
    sensor = scene.sensors()[0]
    params = mi.traverse(sensor)
    out, times = {}, []
    for i, c in enumerate(cams):
        params["to_world"] = mi.ScalarTransform4f(np.asarray(c["to_world"]).tolist())
        params.update()
        t = time.perf_counter()
        img = mi.render(scene, sensor=sensor, seed=seed + 1000 * i)
        dr.eval(img)
        times.append(time.perf_counter() - t)
        out[c["name"]] = np.asarray(img, np.float32)[..., :3]
    return out, float(np.median(times))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--comp", type=Path, required=True)
    ap.add_argument("--rays", type=int, nargs="+", default=[64, 256, 1024])
    ap.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    a = ap.parse_args(argv)
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.core.exr import read_image as read_exr
    from comgs_dr.data import comp_folder
    from comgs_dr.data.images import read_image
    manifest = comp_folder.read_manifest(a.comp)
    cams = comp_folder.camera_source(a.data / "comp", manifest.get("world_from_source"))
    gt, masks = {}, {}
    for c in cams:
        gt[c["name"]] = read_exr(a.data / "comp" / "gt" / f"{c['name']}.exr")[..., :3]
        m = read_image(a.data / "comp" / "mask" / f"{c['name']}.png")
        masks[c["name"]] = (m[..., 0] if m.ndim == 3 else m) > 0.99
        c["height"], c["width"] = masks[c["name"]].shape
    truth = np.concatenate([gt[n][masks[n]] for n in gt]).mean(0)
    print(f"truth mean colour in the object's pixels: {np.round(truth, 4).tolist()}")
    print(f"{'variant':8} {'rays':>5} {'R':>6} {'G':>6} {'B':>6} {'noise':>6} {'s/frame':>8}")
    rows = []
    plans = [("paste", a.rays[0])] + [("sop", r) for r in a.rays]
    for variant, rays in plans:
        one, dt = render(a.comp, cams, variant, rays, 0)
        mean = np.concatenate([one[n][masks[n]] for n in one]).mean(0)
        noise = float("nan")
        if variant != "paste":
            two, _ = render(a.comp, cams, variant, rays, 7)
            diff = np.concatenate([(one[n] - two[n])[masks[n]] for n in one])
            noise = float(diff.std() / np.sqrt(2) / max(mean.mean(), 1e-6))
        ratio = mean / np.maximum(truth, 1e-6)
        print(f"{variant:8} {rays:5d} {ratio[0]:6.3f} {ratio[1]:6.3f} {ratio[2]:6.3f} "
              f"{noise:6.3f} {dt:8.2f}", flush=True)
        rows.append({"variant": variant, "rays": rays, "ratio": ratio.tolist(),
                     "noise": noise, "frame_seconds": dt})
    if a.out:
        a.out.write_text(json.dumps({"truth": truth.tolist(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
