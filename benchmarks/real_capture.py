"""Step 1 on real phone captures (issue 48): `comgs sfm` then `comgs reconstruct --scene`,
held-out PSNR (every 8th registered photo by name held out, as the COLMAP loader splits),
raw and colour-corrected, for the variants of docs/real_capture.md; prints the table.

Cases (from one 360° capture without poses, e.g. data/captures/plush_phone):

* ``fwd20``: 20 consecutive photos (``--first``, by file name = capture order; 8..27 of the
  plush capture span ~90° of its orbit) resized to 504 px on the long side: a stand-in for
  a forward-facing capture of 20 photos at 504 px.
* ``full640``: every photo, `comgs sfm --max-size 640`: the 360° case.

Variants of step 1: ``sparse`` (the SfM points only: ``--init-sweep-points 0``, the
behaviour before), ``default`` (the scene preset's defaults: SfM points + plane-swept fill),
``exposure`` (default + ``--exposure true``).

    python benchmarks/real_capture.py --capture data/captures/plush_phone --work /tmp/rc \\
        --cases fwd20 --variants sparse,default,exposure -r 2 --iterations 1000

Finished steps are reused (an sfm.json, a run's train_log.json); delete them to redo.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
IMAGE_EXT = (".jpg", ".jpeg", ".png")
VARIANTS = {"sparse": ["--init-sweep-points", "0"], "default": [],
            "exposure": ["--exposure", "true"]}


def _cli(*args) -> float:
    """Run ``python -m comgs_dr.cli ARGS`` (this checkout first on the path); seconds."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    t = time.time()
    subprocess.run([sys.executable, "-m", "comgs_dr.cli", *map(str, args)], check=True, env=env)
    return time.time() - t


def subset_photos(src: Path, out: Path, first: int, count: int, size: int) -> Path:
    """``count`` consecutive photos from ``first`` (name order), upright and resized to
    ``size`` px on the long side, into ``out``."""
    from PIL import Image, ImageOps
    names = sorted(p for p in src.iterdir() if p.suffix.lower() in IMAGE_EXT)[first:first + count]
    out.mkdir(parents=True, exist_ok=True)
    for p in names:
        dst = out / p.name
        if dst.exists():
            continue
        im = ImageOps.exif_transpose(Image.open(p)).convert("RGB")
        s = size / max(im.size)
        im.resize((round(im.width * s), round(im.height * s)), Image.LANCZOS).save(dst, quality=95)
    return out


def run_sfm(photos: Path, data: Path, max_size: int | None) -> dict:
    if not (data / "sfm.json").exists():
        extra = ["--max-size", max_size] if max_size else []
        _cli("sfm", photos, "--out", data, "--quiet", *extra)
    rep = json.loads((data / "sfm.json").read_text())
    return {"photos": rep["given"], "registered": rep["registered"],
            "sfm_s": rep["seconds"]["total"], "points": rep["points"],
            "px": max(rep["loads_as"]["width"], rep["loads_as"]["height"])}


def run_step1(data: Path, run: Path, variant: str, scale: int, iterations: int,
              extra: list[str]) -> dict:
    log_path = run / "train_log.json"
    if not log_path.exists():
        _cli("reconstruct", data, "--out", run, "--scene", "-r", scale, "--iterations", iterations,
             "--eval-views", 16, "--quiet", *VARIANTS[variant], *extra)
    log = json.loads(log_path.read_text())
    s = log["summary"]
    tests = [r["psnr_test"] for r in log["log"] if "psnr_test" in r] + [s["psnr_test"]]
    best_it = max((r for r in log["log"] if "psnr_test" in r), key=lambda r: r["psnr_test"],
                  default={"iteration": s["iterations"]})["iteration"]
    return {"iterations": s["iterations"], "train_s": s["train_seconds"],
            "surfels": s["surfels"], "test_views": s["views"],
            "best": max(tests), "best_it": best_it, "final": s["psnr_test"],
            "final_cc": s.get("psnr_test_exposure"), "train_psnr": s["psnr_select"]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--capture", type=Path, default=REPO / "data" / "captures" / "plush_phone",
                    help="capture folder (photos in it or in its images/)")
    ap.add_argument("--work", type=Path, required=True, help="output folder")
    ap.add_argument("--cases", default="fwd20,full640")
    ap.add_argument("--variants", default="sparse,default,exposure")
    ap.add_argument("--first", type=int, default=8, help="fwd20: first photo (name order)")
    ap.add_argument("-r", "--resolution-scale", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--extra", default="", help="more `comgs reconstruct` flags, one string")
    a = ap.parse_args(argv)
    src = a.capture / "images" if (a.capture / "images").is_dir() else a.capture
    rows = []
    for case in a.cases.split(","):
        if case == "fwd20":
            photos = subset_photos(src, a.work / "fwd20_photos", a.first, 20, 504)
            info = run_sfm(photos, a.work / "fwd20_sfm", None)
        elif case == "full640":
            info = run_sfm(src, a.work / "full640_sfm", 640)
        else:
            raise SystemExit(f"unknown case {case!r}: fwd20, full640")
        for v in a.variants.split(","):
            if v not in VARIANTS:
                raise SystemExit(f"unknown variant {v!r}: {', '.join(VARIANTS)}")
            r = run_step1(a.work / f"{case}_sfm", a.work / f"{case}_r{a.resolution_scale}_{v}", v,
                          a.resolution_scale, a.iterations, a.extra.split())
            rows.append({"case": case, "variant": v, **info, **r})
            print(json.dumps(rows[-1]), flush=True)
    print("\n| capture | photos | px | registered | sfm s | step 1 | iterations | s | surfels "
          "| held-out PSNR best (it) | final | final, colour-corrected | train views |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        cc = "–" if r["final_cc"] is None else f"{r['final_cc']:.2f}"
        print(f"| {r['case']} | {r['photos']} | {r['px']}/{a.resolution_scale} | "
              f"{r['registered']}/{r['photos']} | {r['sfm_s']:.0f} | {r['variant']} | "
              f"{r['iterations']} | {r['train_s']:.0f} | {r['surfels']} | {r['best']:.2f} "
              f"({r['best_it']}) | {r['final']:.2f} | {cc} | {r['train_psnr']:.2f} |")


if __name__ == "__main__":
    main()
