"""Does the light head err inside a scene, or only through step 1? Its gains on the true
light at a placement against the bare map.

For each map cached by ``benchmarks/recon_light_e2e.py`` (``--cache``: its ``--out`` folder,
holding ``<map stem>/probe_256.npy``, the light path-traced at the object's placement in the
dataset's scene without the object), the shipped head reads, fully observed and exposed to
EV 0 (white level 1, display values):

* the probe at the placement, at 256 and 128 rows (the scene's ground, wall and box around
  the viewpoint, no reconstruction involved);
* the bare map at the same exposure as the dataset (``pano_data.auto_exposure`` × the
  ``--exposure`` the benchmark used), at 256 rows: what the head was trained on.

Per clipped region (largest observed power first, at most ``--regions``): the predicted gain
P_true / P_seen and, in brackets, the true one (the HDR panorama's luminance power in the
region over that of its EV-0 pixels). The label is the map's (``pano_data.label_of``).
Seconds per map; no rendering.

    python benchmarks/light_head_in_scene.py --cache out/recon_light_e2e [--maps a.exr ...]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def gains(hdr: np.ndarray, head, label: int, k: int) -> list[tuple[float, float, float]]:
    """[(solid angle, predicted gain, true gain)] of the ``k`` strongest clipped regions of
    the linear equirect ``hdr`` [H, W, 3] seen whole at EV 0."""
    from comgs_dr.core.colorspace import LUMA, srgb_encode
    from comgs_dr.core.equirect import pixel_solid_angles
    from comgs_dr.lighting import lights as L
    h, w = hdr.shape[:2]
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    ldr = srgb_encode(np.clip(hdr, 0.0, 1.0)).astype(np.float32)
    out = []
    for p in L.predict_lobes(ldr, np.ones((h, w), np.float32), head, label)[:k]:
        reg = p["region"]
        seen = float((np.clip(hdr, 0.0, 1.0) @ LUMA * dw)[reg].sum())
        true = float((hdr @ LUMA * dw)[reg].sum())
        out.append((p["solid_angle"], p["gain"], true / max(seen, 1e-12)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", required=True, help="recon_light_e2e's --out folder")
    ap.add_argument("--maps", nargs="*", default=None, help="map files (default: every "
                    "cached map found among the shared maps)")
    ap.add_argument("--exposure", type=float, default=1.0, help="recon_light_e2e's --exposure")
    ap.add_argument("--regions", type=int, default=3)
    ap.add_argument("--light-head", default=None, help="light-head weights (default: shipped)")
    a = ap.parse_args(argv)

    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.data.synthetic import shared_data_dir
    from comgs_dr.lighting import envmap, pano_data
    from comgs_dr.lighting import lights as L
    from comgs_dr.lighting.completion import LABELS
    from comgs_dr.lighting.hdr import area_resize_equirect

    cache = Path(a.cache)
    maps = [Path(m) for m in a.maps] if a.maps else [
        p for p in pano_data.map_files(shared_data_dir() / "hdri")
        if (cache / p.stem / "probe_256.npy").is_file()]
    if not maps:
        raise SystemExit(f"no cached probe_256.npy under {cache} for the given maps")
    fixed = None if a.light_head is None else L.load_head(a.light_head)

    def head_for(stem):
        """--light-head, or the shipped head (its fold without ``stem`` for a held-out map)."""
        return fixed if fixed is not None else L.load_head(L.held_out_head(stem))

    def cell(rows):
        return ", ".join(f"{g:.0f} ({t:.0f})" for _, g, t in rows) or "no clipped region"
    print("| map (label) | probe at the placement, 256 rows | bare map, 256 rows | "
          "probe, 128 rows |")
    print("|---|---|---|---|")
    for m in maps:
        probe = np.load(cache / m.stem / "probe_256.npy").astype(np.float64)
        env = envmap.read_envmap_file(m)[0]
        bare = env * pano_data.auto_exposure(env) * a.exposure
        label = pano_data.label_of(m.stem)
        lab = LABELS[label]
        head = head_for(m.stem)
        cols = [gains(probe, head, lab, a.regions),
                gains(area_resize_equirect(bare, 256, 512), head, lab, a.regions),
                gains(area_resize_equirect(probe, 128, 256), head, lab, a.regions)]
        print(f"| {m.stem} ({label}) | " + " | ".join(cell(c) for c in cols) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
