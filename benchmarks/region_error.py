"""What a composite's object+shadow error is made of, and how step 2 split light and albedo.

    python benchmarks/region_error.py --data DS/comp --comp COMP [--variants sop,paste]
        [--material RUN/material ...]

``--data``: a composition dataset's ``comp/`` folder (``gt/``, ``empty/``, ``mask/``);
``--comp``: a composition with ``renders/<variant>/`` (``render-comp``). Per variant, over
the object+shadow region of ``eval.comp_region.regions`` (the PSNR ``render-comp`` reports
as ``psnr_region``, on the 8-bit sRGB images, mean over frames):

* the share of the region's squared error on the object's pixels, on the truth's shadow
  pixels and on the rest of the region, and the region PSNR with that part replaced by the
  truth (what a perfect object, or a perfect shadow, would score);
* the region PSNR with the object's mean linear colour scaled per channel to the truth's
  (what a right hue and level alone would give: the rest is the object's shading and
  texture), and those per-channel gains (truth / ours).

``--material``: step-2 folders (``comgs decompose``'s output) whose split of the capture's
shading between the learnt light and the albedo is reported: the learnt map's luminance
irradiance max / min over 200 normals (a flat light: 1), the opaque surfels' albedo log
luminance spread, and its slope on the step-1 colour's (1: the albedo keeps all of the
capture's shading; 0 on a one-colour object: the light explains it).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np

import comgs_dr
from comgs_dr.core.colorspace import srgb_decode, srgb_encode
from comgs_dr.core.exr import read_image
from comgs_dr.eval import comp_region
from comgs_dr.eval.lighting_metrics import irradiance_contrast
from comgs_dr.eval.metrics import albedo_shading_split
from comgs_dr.surfels import load_ply


def _srgb(path: Path) -> np.ndarray:
    return iio.imread(path)[..., :3].astype(np.float64) / 255.0


def _mask(folder: Path, name: str) -> np.ndarray:
    m = iio.imread(next(folder.glob(f"{name}.png")))
    return (m[..., -1] if m.ndim == 3 else m) > 127


def _psnr(sq_err_sum: float, n: int) -> float:
    return float(10.0 * np.log10(n / max(sq_err_sum, 1e-12)))


def frame_split(pred: np.ndarray, gt: np.ndarray, empty_lin: np.ndarray,
                obj: np.ndarray) -> dict:
    """One frame's region error split (``pred``/``gt`` [H, W, 3] sRGB in [0, 1], ``empty_lin``
    linear, ``obj`` [H, W] bool): region PSNR, per part its error share and the region PSNR
    without its error, the PSNR with the object's linear colour gain-corrected, the gains."""
    shadow, region, _ = comp_region.regions(srgb_decode(gt), empty_lin, obj)
    err = ((pred - gt) ** 2).mean(-1)
    n, total = int(region.sum()), float(err[region].sum())
    out = {"region": _psnr(total, n)}
    for part, m in {"object": obj, "shadow": shadow, "rest": ~obj & ~shadow}.items():
        e = float(err[region & m].sum())
        out[f"{part}_share"] = e / max(total, 1e-12)
        out[f"{part}_perfect"] = _psnr(total - e, n)
    gl, pl = srgb_decode(gt[obj]), srgb_decode(pred[obj])
    gain = gl.mean(0) / np.maximum(pl.mean(0), 1e-6)
    fixed = pred.copy()
    fixed[obj] = np.clip(srgb_encode(np.clip(pl * gain, 0.0, None)), 0.0, 1.0)
    out["colour_fixed"] = _psnr(float(((fixed - gt) ** 2).mean(-1)[region].sum()), n)
    out["gain"] = gain
    return out


def split(data: Path, comp: Path, variant: str) -> dict:
    """:func:`frame_split` averaged over the frames of ``data/gt``."""
    rows = []
    for g in sorted((data / "gt").glob("*.png")):
        name = g.stem
        rows.append(frame_split(_srgb(comp / "renders" / variant / f"{name}.png"), _srgb(g),
                                read_image(data / "empty" / f"{name}.exr")[..., :3],
                                _mask(data / "mask", name)))
    return {k: np.mean([r[k] for r in rows], 0) for k in rows[0]}


def material_split(folder: Path) -> dict:
    """The learnt map's irradiance contrast and ``eval.metrics.albedo_shading_split`` of a
    step-2 folder."""
    env = folder / "envmap_equirect.exr"
    return {"env_contrast": irradiance_contrast(read_image(env)[..., :3]) if env.is_file()
            else np.nan, **albedo_shading_split(load_ply(str(folder / "point_cloud.ply")))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--comp", type=Path, default=None)
    ap.add_argument("--variants", default="sop,paste")
    ap.add_argument("--material", type=Path, nargs="*", default=[])
    a = ap.parse_args(argv)
    if a.data is not None and a.comp is not None:
        print(f"{'variant':<10}{'region':>8}{'object %':>10}{'→ perfect':>10}{'shadow %':>10}"
              f"{'→ perfect':>10}{'rest %':>8}{'colour fixed':>14}  gains (truth / ours)")
        for v in a.variants.split(","):
            if not (a.comp / "renders" / v).is_dir():
                print(f"{v:<10}  (no renders)")
                continue
            s = split(a.data, a.comp, v)
            print(f"{v:<10}{s['region']:>8.2f}{100 * s['object_share']:>10.0f}"
                  f"{s['object_perfect']:>10.2f}{100 * s['shadow_share']:>10.0f}"
                  f"{s['shadow_perfect']:>10.2f}{100 * s['rest_share']:>8.0f}"
                  f"{s['colour_fixed']:>14.2f}  {', '.join(f'{g:.2f}' for g in s['gain'])}")
    if a.material:
        comgs_dr.set_variant("llvm_ad_rgb")           # load_ply builds Dr.Jit arrays
        print(f"\n{'step 2':<40}{'map E max/min':>14}{'albedo spread':>15}{'step 1':>8}"
              f"{'slope':>7}  albedo median")
        for m in a.material:
            s = material_split(m)
            print(f"{str(m)[-40:]:<40}{s['env_contrast']:>14.2f}{s['albedo_spread']:>15.2f}"
                  f"{s['step1_spread']:>8.2f}{s['slope']:>7.2f}  "
                  f"{', '.join(f'{x:.3f}' for x in s['albedo_median'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
