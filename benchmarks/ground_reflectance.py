"""What real surroundings reflect: E_down / E_up of each shared HDR map, per channel.

The irradiance on a surface facing down over the one facing up is what the ground (and
everything below the horizon) reflects of the light above: its effective albedo. The
unseen-sky lift (``lighting.clear_sky.ground_albedo_floor``) raises a sky nobody saw until
this ratio, at the placement, is at most ``MAX_GROUND_ALBEDO``; this table is the evidence
for that ceiling, from real captures rather than our own scenes.

    python benchmarks/ground_reflectance.py [--maps DIR]     # ~5 s
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np


def down_over_up(path: Path) -> np.ndarray:
    """E_down / E_up per channel of an equirect map (rows: zenith to nadir)."""
    import mitsuba as mi
    bmp = mi.Bitmap(str(path)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32)
    rad = np.asarray(bmp, np.float64)
    h = rad.shape[0]
    theta = (np.arange(h) + 0.5) / h * np.pi
    w = (np.sin(theta) * np.cos(theta))[:, None, None]          # solid angle × cos, signed
    e_up = (rad * np.maximum(w, 0)).sum((0, 1))
    e_down = (rad * np.maximum(-w, 0)).sum((0, 1))
    return e_down / np.maximum(e_up, 1e-300)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(os.environ.get("COMGS_DATA_DIR", Path(__file__).parents[2] / "shared" / "data"))
    ap.add_argument("--maps", type=Path, default=default / "hdri")
    a = ap.parse_args(argv)
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    from comgs_dr.lighting.clear_sky import MAX_GROUND_ALBEDO
    files = sorted(p for p in a.maps.iterdir() if p.suffix.lower() in (".exr", ".hdr"))
    if not files:
        raise SystemExit(f"no .exr/.hdr maps in {a.maps}")
    print(f"{'map':<34}{'R':>7}{'G':>7}{'B':>7}{'max':>7}")
    peaks = []
    for f in files:
        r = down_over_up(f)
        peaks.append(r.max())
        print(f"{f.name:<34}" + "".join(f"{x:>7.3f}" for x in r) + f"{r.max():>7.3f}")
    peaks = np.array(peaks)
    print(f"\n{len(files)} maps: brightest channel median {np.median(peaks):.3f}, quartiles "
          f"{np.percentile(peaks, 25):.3f} / {np.percentile(peaks, 75):.3f}; "
          f"{int((peaks <= MAX_GROUND_ALBEDO + 0.01).sum())} of {len(files)} at most "
          f"MAX_GROUND_ALBEDO {MAX_GROUND_ALBEDO} (+0.01)")


if __name__ == "__main__":
    main()
