"""Forward-facing captures with a real sky, end to end: step 1 with and without the far-field
initialisation, then the lighting at a placement in the scene against the true light.

For each map (``--maps NAME[:DEG]``, DEG the map's turn about +Z so its sun is in view):

1. ``make_llff_dataset`` renders a forward-facing capture (``--rows`` × ``--cols`` views,
   no backdrop wall, auto-exposed map) and the true light at ``llff_synthetic.PLACEMENT``
   in the reconstruction's frame (``probes/center.exr``);
2. step 1 (preset "scene", ``background="env"``, ``-r 2``) runs twice, ``init_far_field``
   on and off (``train.init.near_far_points(far_field=...)``);
3. ``estimate_light`` (defaults, ``exclude_radius`` 0.05) at the placement, scored by
   ``eval.lighting_metrics.compare_maps``.

One row per map and setting: test PSNR, the open sky at the placement
(``meta.open_sky_fraction``), the dominant light's angle, the E(light)/E(up) error and the
power ratio. Datasets and runs are cached in ``--out``.

    python benchmarks/llff_light_e2e.py                  # venice, sunrise, kiara turned 162°
    python benchmarks/llff_light_e2e.py --maps blender_city.exr:90 --iterations 400
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np

DEFAULT_MAPS = ("venice_sunset_1k.hdr:0", "blender_sunrise.exr:0", "kiara_1_dawn_1k.hdr:162")


def parse_map(spec: str, folder: Path) -> tuple[Path, float]:
    """(map path, turn in degrees) of ``NAME[:DEG]``; NAME in ``folder`` unless a path."""
    name, _, deg = spec.partition(":")
    p = Path(name) if Path(name).is_file() else folder / name
    if not p.is_file():
        raise FileNotFoundError(f"llff_light_e2e: map not found: {p}")
    return p, float(deg or 0.0)


def build(p: Path, turn: float, out: Path, a) -> Path:
    """The dataset folder of one map (cached)."""
    from comgs_dr.data.llff_synthetic import LLFFDatasetConfig, make_llff_dataset
    ds = out / "dataset"
    if not (ds / "probes" / "probes.json").is_file():
        make_llff_dataset(LLFFDatasetConfig(
            out_dir=ds, rows=a.rows, cols=a.cols, width=a.width, height=a.height,
            downscales=(2,), spp=a.spp, envmap=str(p), envmap_rotate_deg=turn, backdrop=False,
            probe_height=128, seed=a.seed))
    return ds


def reconstruct(ds: Path, run: Path, far: bool, a) -> float:
    """Step 1 (cached); returns its test PSNR."""
    from comgs_dr.data.load import load_dataset
    from comgs_dr.stages.reconstruct import RadianceConfig, train_radiance
    from comgs_dr.train.run import write_run_info
    if not (run / "point_cloud.ply").exists():
        write_run_info(run, ds, "scene", 2, False)
        with warnings.catch_warnings():         # "scene preset without dataset points": known
            warnings.simplefilter("ignore", UserWarning)
            train_radiance(load_dataset(ds, resolution_scale=2), run, RadianceConfig.from_preset(
                "scene", iterations=a.iterations, eval_every=a.iterations, eval_views=2,
                seed=a.seed, background="env", init_far_field=far), progress=False)
    return float(json.loads((run / "train_log.json").read_text())["summary"]["psnr_test"])


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--maps", nargs="*", default=list(DEFAULT_MAPS), metavar="NAME[:DEG]")
    ap.add_argument("--maps-dir", default=None, help="folder of the maps (default: the "
                    "shared data's hdri/)")
    ap.add_argument("--out", default="out/llff_light_e2e", help="cache of datasets and runs")
    ap.add_argument("--rows", type=int, default=3)
    ap.add_argument("--cols", type=int, default=4)
    ap.add_argument("--width", type=int, default=128, help="capture width (trained at half)")
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--iterations", type=int, default=800)
    ap.add_argument("--trace-res", type=int, default=256, help="trace height (width 2x)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.data.synthetic import shared_data_dir
    from comgs_dr.eval.lighting_metrics import at_coarser, compare_maps
    from comgs_dr.lighting.envmap import read_envmap_file
    from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light
    logging.getLogger("comgs_dr").setLevel(logging.ERROR)      # the table says it all
    folder = Path(a.maps_dir) if a.maps_dir else shared_data_dir() / "hdri"
    maps = [parse_map(s, folder) for s in a.maps]                # every map checked first
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; {a.rows}x{a.cols} views "
          f"at {a.width}x{a.height} (trained at half), step 1 {a.iterations} it\n")
    print("| map | far-field init | test PSNR dB | open sky | light angle ° | "
          "E(light)/E(up) error | power est/true | s |\n|---|---|---|---|---|---|---|---|",
          flush=True)
    rows = []
    for p, turn in maps:
        out = Path(a.out) / f"{p.stem}_{turn:g}"
        ds = build(p, turn, out, a)
        pos = json.loads((ds / "probes" / "probes.json").read_text())["center"]["position"]
        truth = read_envmap_file(ds / "probes" / "center.exr")[0].astype(np.float64)
        for far in (True, False):
            t0 = time.perf_counter()
            psnr = reconstruct(ds, out / f"run_far_{'on' if far else 'off'}", far, a)
            r = estimate_light(str(out / f"run_far_{'on' if far else 'off'}" / "point_cloud.ply"),
                               pos, EstimateConfig(width=2 * a.trace_res, height=a.trace_res,
                                                   oct_res=64, exclude_radius=0.05))
            m = compare_maps(*at_coarser(r["hdr"], truth))
            re_, rg = m.get("light_up_irradiance_ratio_est"), m.get("light_up_irradiance_ratio_gt")
            err = None if re_ is None or rg is None else re_ / rg - 1.0
            row = {"map": f"{p.stem}:{turn:g}", "far_field": far, "psnr_test": psnr,
                   "open_sky": r["meta"]["open_sky_fraction"],
                   "light_angle_deg": m.get("light_angle_deg"), "ratio_err": err,
                   "power": m["power_ratio_est_gt"], "seconds": time.perf_counter() - t0}
            rows.append(row)
            fmt = lambda v, f: "n/a" if v is None else format(v, f)   # noqa: E731
            print(f"| {row['map']} | {'on' if far else 'off'} | {psnr:.2f} | "
                  f"{fmt(row['open_sky'] and 100 * row['open_sky'], '.1f')} % | "
                  f"{fmt(row['light_angle_deg'], '.0f')} | "
                  f"{fmt(err and 100 * err, '+.0f')} % | {row['power']:.2f} | "
                  f"{row['seconds']:.0f} |", flush=True)
    return rows


if __name__ == "__main__":
    main()
