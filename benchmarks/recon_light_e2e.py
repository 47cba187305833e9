"""End to end through step 1: a real map lights a scene, step 1 reconstructs it, and
``estimate_light`` at the placement is scored against the light that arrives there.

For each map (default: the held-out outdoor shared maps, ``pano_data.HELD_OUT``):

1. ``make_composition_dataset`` path-traces the scene capture under the map (exposed by
   ``pano_data.auto_exposure`` so the sky is in range and the sun clips), with the demo's
   camera set: views looking down at the ground and ``--sky-views`` eye-height views over
   the horizon that see the sky (and the sun where it is low enough);
2. step 1 (``train_radiance``, preset "scene", learnt sky behind the surfels) reconstructs it;
3. ``estimate_light`` runs at the placement of the dataset's object with each method, and
   ``eval.lighting_metrics.compare_maps`` scores the result against the true light at the
   placement: the scene without the object, path-traced from there along every direction
   (``data.placement_probe``; ``--truth map``: the exposed map, as before, which ignores the
   scene's occlusion and reflections and has the map's own ground below the horizon). The
   scores: the issue's E(facing the true dominant light) / E(facing up), the dominant
   light's angle and the total power ratio.

Methods: ``default`` (what ``estimate-light`` does: ``backends.default_backend`` and the light
head), ``net+lights``, ``net``, ``push_pull`` and ``push_pull+lights``. ``recon_light_e2e.png``
in ``--out`` shows, per map, the placement's input with the recorded clipped rays, the true
light and the default's estimate.

This is the check ``sun_e2e.py`` cannot make: its scene is a perfect reconstruction, here
the sun goes through LDR captures and step 1's optimisation (blur, a learnt background).

    python benchmarks/recon_light_e2e.py [--maps a.exr ...] [--iterations 800] [--out DIR]

The shipped light head was fitted on every shared map; with ``--light-head default`` a map
whose fold of it is kept (the held-out maps, ``cv_heads.held_out_head``) is estimated with
that fold, the head fitted the same way without the map (a comment line says so).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np


def build_run(map_path: Path, out: Path, a) -> tuple[Path, np.ndarray, float]:
    """(step-1 run folder, object centre [3], map exposure) for one map, cached in ``out``."""
    from comgs_dr.data import procedural
    from comgs_dr.data.composition_dataset import (CompositionDatasetConfig,
                                                   make_composition_dataset)
    from comgs_dr.data.load import load_dataset
    from comgs_dr.lighting import envmap, pano_data
    from comgs_dr.stages.reconstruct import RadianceConfig, train_radiance
    from comgs_dr.train.run import write_run_info
    ds, run = out / "dataset", out / "scene_run"
    env = envmap.read_envmap_file(map_path)[0].astype(np.float64)
    scale = pano_data.auto_exposure(env) * a.exposure
    if not (ds / "composition.json").exists():
        out.mkdir(parents=True, exist_ok=True)
        mesh = procedural.procedural_object_yup(out / "object.ply")
        make_composition_dataset(CompositionDatasetConfig(
            out_dir=ds, objects=(str(mesh),), scene_map=map_path, object_map=map_path,
            resolution=a.res, scene_views=a.views, object_views=1, test_views=2, spp=a.spp,
            sfm_points=5000, seed=a.seed, scene_elevation_deg=(30.0, 70.0),
            sky_views=a.sky_views, sky_pitch_deg=(10.0, 40.0), scene_envmap_scale=scale,
            sun_view=not a.no_sun_view),
            progress=False)
    if not (run / "point_cloud.ply").exists():
        write_run_info(run, ds / "scene", "scene", 1, False)
        train_radiance(load_dataset(ds / "scene"), run, RadianceConfig.from_preset(
            "scene", iterations=a.iterations, eval_every=a.iterations, eval_views=2,
            seed=a.seed, background="env", env_resolution=a.env_resolution), progress=False)
    tr = json.loads((ds / "transform.json").read_text())
    m = np.array(next(iter(tr.values()))["transform"], np.float64).reshape(4, 4)
    return run, m[:3, 3], scale


def _frac(x) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def true_light(map_path: Path, out: Path, scale: float, kind: str) -> np.ndarray:
    """The reference: the light path-traced at the placement in the dataset's scene without
    the object (``data.placement_probe``, 256 rows, 64 strata per pixel; cached in ``out``),
    or the exposed map itself (``kind`` "map": no occlusion by the scene, the map's own
    ground below the horizon)."""
    from comgs_dr.data import placement_probe
    from comgs_dr.lighting import envmap
    if kind == "map":
        return envmap.read_envmap_file(map_path)[0].astype(np.float64) * scale
    f = out / "probe_256.npy"
    if not f.is_file():
        np.save(f, placement_probe.placement_probe(out / "dataset", height=256, spp_side=8))
    return np.load(f).astype(np.float64)


def save_figure(panels: list, path: Path) -> Path:
    """One row per map: the placement's EV-0 input (recorded clipped rays in red), the true
    light and the default's estimate, both at the truth's exposure (tone-mapped)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from comgs_dr.core.colorspace import LUMA, tonemap
    from comgs_dr.lighting.hdr import area_resize_equirect
    fig, axes = plt.subplots(len(panels), 3, figsize=(12, 2.2 * len(panels)), squeeze=False)
    for row, (name, rgb, clip, truth, est, err) in zip(axes, panels):
        h, w = rgb.shape[:2]
        t = area_resize_equirect(truth, h, w)
        k = 0.5 / max(float(np.percentile(t @ LUMA, 90)), 1e-6)
        inp = np.asarray(rgb, np.float64).copy()
        if clip is not None:
            inp[clip.max(-1) >= 0.5] = [1.0, 0.0, 0.0]
        for ax, img, title in ((row[0], inp, f"{name}: input at the placement (red: "
                                "recorded clipped rays)"),
                               (row[1], tonemap(np.clip(t * k, 0, None)), "true light"),
                               (row[2], tonemap(np.clip(est * k, 0, None)),
                                f"estimate (default): E ratio {100 * err:+.0f} %")):
            ax.imshow(np.clip(img, 0, 1))
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--maps", nargs="*", default=None, help="equirect maps (default: the "
                    "held-out outdoor shared maps)")
    ap.add_argument("--out", default="out/recon_light_e2e", help="cache of datasets and runs")
    ap.add_argument("--res", type=int, default=64, help="capture resolution")
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--sky-views", type=int, default=12)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--iterations", type=int, default=800)
    ap.add_argument("--env-resolution", type=int, default=128, help="step 1's sky texels "
                    "per side (the demo's 128; reconstruct's default is 64)")
    ap.add_argument("--exposure", type=float, default=1.0, help="times the auto exposure")
    ap.add_argument("--trace-res", type=int, default=512, help="trace height (width 2x; "
                    "512: estimate-light's default 1024x512)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--label", choices=("name", "auto", "outdoor", "indoor", "unknown"),
                    default="name", help="estimate-light's scene label (name: the map's, "
                    "pano_data.label_of; auto: classified from the trace, lighting.scene_label)")
    ap.add_argument("--truth", choices=("probe", "map"), default="probe", help="score against "
                    "the light path-traced at the placement in the scene (default) or the map")
    ap.add_argument("--weights", default=None, help="completion checkpoint (default: shipped)")
    ap.add_argument("--light-head", default="default", help="light-head weights (default: "
                    "the shipped head)")
    ap.add_argument("--trust-brackets", type=float, default=None, help="EstimateConfig."
                    "light_trust_brackets (default: its default)")
    ap.add_argument("--light-head-rows", type=int, default=None, help="EstimateConfig."
                    "light_head_rows: the head reads at most this many rows (default: its "
                    "default)")
    ap.add_argument("--no-sun-view", action="store_true", help="do not aim the first sky "
                    "view at the sun (a low sun may then be missed by every view)")
    a = ap.parse_args(argv)
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.lighting import pano_data
    from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light
    from comgs_dr.train import background as bgenv
    from sun_e2e import TABLE_HEAD, e2e_methods, map_head, outdoor_maps, print_summary, score
    maps = outdoor_maps(a.maps)
    methods, be = e2e_methods(head=a.light_head, weights=a.weights)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; capture {a.res} px, "
          f"{a.views}+{a.sky_views} views, step 1 {a.iterations} it; trace "
          f"{2 * a.trace_res}x{a.trace_res}\n", flush=True)
    print(TABLE_HEAD, flush=True)
    rows, panels = [], []
    for p in maps:
        t0 = time.perf_counter()
        run, pos, scale = build_run(p, Path(a.out) / p.stem, a)
        t_build = time.perf_counter() - t0
        truth = true_light(p, Path(a.out) / p.stem, scale, a.truth)
        label = pano_data.label_of(p.stem) if a.label == "name" else a.label
        heads = {"default": map_head(p.stem, "default")} if a.light_head == "default" else {}
        for name, (kind, head) in methods.items():
            t0 = time.perf_counter()
            kw = {} if a.trust_brackets is None else {"light_trust_brackets": a.trust_brackets}
            if a.light_head_rows is not None:
                kw["light_head_rows"] = a.light_head_rows
            cfg = EstimateConfig(width=2 * a.trace_res, height=a.trace_res, oct_res=64,
                                 label=label, light_head=heads.get(head, head), **kw)
            r = estimate_light(str(run / "point_cloud.ply"), pos, cfg, be[kind])
            dt = time.perf_counter() - t0
            row = score(p.stem, name, r, truth, dt)
            rows.append(row)
            if name == "default":
                if r["meta"].get("p_outdoor") is not None:
                    print(f"<!-- {p.stem}: label auto -> {r['meta']['label']} "
                          f"(p(outdoor) {r['meta']['p_outdoor']:.2f}) -->", flush=True)
                print(f"<!-- {p.stem}: upper hemisphere seen {r['meta']['seen_sky_fraction']:.2f} "
                      f"(open sky {_frac(r['meta']['open_sky_fraction'])}), of it "
                      f"clipped {r['meta']['clipped_sky_fraction']:.2f} -->", flush=True)
                rec = bgenv.load_clipped(run)
                clip = None if rec is None else bgenv.splat_record(rec, *r["hdr"].shape[:2])
                panels.append((p.stem, r["input"]["rgb"], clip, truth, r["hdr"],
                               row["ratio_err"]))
        print(f"<!-- {p.stem}: dataset + step 1 {t_build:.0f} s -->", flush=True)
    print(f"\nfigure: {save_figure(panels, Path(a.out) / 'recon_light_e2e.png')}")
    print_summary(rows, methods)
    return rows


if __name__ == "__main__":
    main()
