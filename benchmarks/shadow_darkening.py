"""How dark a composite's shadow is, three ways, in the truth's shadow pixels.

    python benchmarks/shadow_darkening.py --data DS/comp --comp COMP [--variants sop,trace]
        [--unshadowed paste] [--unshadowed-dir DIR]

``--data``: a composition dataset's ``comp/`` folder (``gt/``, ``empty/``, ``mask/``);
``--comp``: a composition with ``renders/<variant>/`` (``render-comp``). For each variant,
over the truth's shadow pixels (``eval.comp_region.regions``: truth / empty < 0.7 outside
the object), the depth (1 − ours) / (1 − truth) of

* ``per pixel``: the mean of render / the truth's empty scene (``region.shadow_depth``);
* ``area``: Σ render / Σ empty (``region.shadow_depth_area``);
* ``own``: the mean of render / our own unshadowed scene, the paste render (the object
  pasted without a shadow; ``--unshadowed-dir`` when it lives elsewhere, e.g. another
  composition of the same scene), against the truth's truth / empty: how much the
  composite darkens the scene it shows, free of step 1's reconstruction of that scene.

Prints a table; the per-pixel and area scores are those ``render-comp`` writes, the third
needs two variants' renders and is measured here.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np

import comgs_dr
from comgs_dr.core.colorspace import luminance, srgb_decode
from comgs_dr.core.exr import read_image
from comgs_dr.eval import comp_region


def _png(path: Path) -> np.ndarray:
    return np.asarray(srgb_decode(iio.imread(path)[..., :3] / 255.0), np.float64)


def _mask(folder: Path, name: str) -> np.ndarray:
    f = next(folder.glob(f"{name}.*"))
    m = iio.imread(f)
    return (m[..., -1] if m.ndim == 3 else m) > 127


def scores(data: Path, comp: Path, variant: str, unshadowed: Path) -> dict:
    """The three depths of ``variant`` (see the module docstring) and the shadow pixels."""
    ours, truth, empty, own = [], [], [], []
    for g in sorted((data / "gt").glob("*.exr")):
        name = g.stem
        gt, emp = read_image(g)[..., :3], read_image(data / "empty" / f"{name}.exr")[..., :3]
        shadow, _, _ = comp_region.regions(gt, emp, _mask(data / "mask", name))
        r = luminance(_png(comp / "renders" / variant / f"{name}.png"))[shadow]
        u = luminance(_png(unshadowed / f"{name}.png"))[shadow]
        ours.append(r)
        truth.append(luminance(gt)[shadow])
        empty.append(luminance(emp)[shadow])
        own.append(r / np.maximum(u, 1e-6))
    ours, truth, empty, own = (np.concatenate(a) for a in (ours, truth, empty, own))
    t_pix = float(np.mean(truth / np.maximum(empty, 1e-6)))
    t_area = float(truth.sum() / empty.sum())

    def depth(v, t):
        return (1.0 - v) / max(1.0 - t, 1e-6)
    return {"pixels": len(ours),
            "per_pixel": depth(float(np.mean(ours / np.maximum(empty, 1e-6))), t_pix),
            "area": depth(float(ours.sum() / empty.sum()), t_area),
            "own": depth(float(np.mean(own)), t_pix)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--comp", type=Path, required=True)
    ap.add_argument("--variants", default="sop,trace")
    ap.add_argument("--unshadowed", default="paste")
    ap.add_argument("--unshadowed-dir", type=Path, default=None)
    a = ap.parse_args(argv)
    comgs_dr.set_variant("llvm_ad_rgb")
    unshadowed = a.unshadowed_dir or a.comp / "renders" / a.unshadowed
    print(f"{'variant':<10}{'pixels':>8}{'per pixel':>11}{'area':>8}{'own':>8}")
    for v in a.variants.split(","):
        if not (a.comp / "renders" / v).is_dir():
            print(f"{v:<10}  (no renders)")
            continue
        s = scores(a.data, a.comp, v, unshadowed)
        print(f"{v:<10}{s['pixels']:>8}{s['per_pixel']:>11.3f}{s['area']:>8.3f}{s['own']:>8.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
