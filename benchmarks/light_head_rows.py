"""At how many panorama rows should the light head read? Its power error per head size.

For each map (default: the held-out shared maps, ``pano_data.HELD_OUT``) at ``--height`` rows,
``--draws`` draws (the first with the whole sphere seen, the others through traced surfel
masks; rotated, re-exposed by 2^U(−1.5, 1.5) around auto exposure), the EV-0 LDR panorama is
read by the shipped head in f×f blocks (``lights.downsample_clipped``, f = 1, 2, 4, 8) and
its predicted power of all clipped regions is compared with the true map's power in those
regions: log(predicted / true). The table gives, per head size, the mean |log error| and
bias over all draws and the mean log error per map. ``estimate_light``'s
``EstimateConfig.light_head_rows`` (256) was chosen from this table.

    python benchmarks/light_head_rows.py [--height 512] [--maps NAME ...] [--draws 6]
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--height", type=int, default=512, help="panorama rows (width 2x)")
    ap.add_argument("--maps", nargs="*", default=None, help="shared map names (default: the "
                    "held-out ones)")
    ap.add_argument("--draws", type=int, default=6, help="draws per map (>= 1)")
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args(argv)
    if a.draws < 1 or a.height % 64:
        raise SystemExit("--draws must be >= 1 and --height a multiple of 64")
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.core.colorspace import LUMA
    from comgs_dr.core.equirect import pixel_solid_angles
    from comgs_dr.data import pano_masks
    from comgs_dr.data.synthetic import shared_data_dir
    from comgs_dr.lighting import completion as C
    from comgs_dr.lighting import lights as L
    from comgs_dr.lighting import pano_data as P
    from comgs_dr.lighting.hdr import expose

    h, t0 = a.height, time.perf_counter()
    names = a.maps or list(P.HELD_OUT)
    rng = np.random.default_rng(a.seed)
    masks = [m["alpha"] for m in pano_masks.mask_bank(max(a.draws - 1, 1), 64, 128,
                                                      seed=a.seed + 72, progress=False)]
    head = L.load_head()
    dw = np.broadcast_to(pixel_solid_angles(h, 2 * h), (h, 2 * h))
    factors = [f for f in (1, 2, 4, 8) if h // f >= 16]
    errs = {f: [] for f in factors}                       # (log error, map)
    for name in names:
        path = next((p for p in (shared_data_dir() / "hdri").glob(name + ".*")), None)
        if path is None:
            raise SystemExit(f"no shared map named {name}")
        hdr = P.load_map(path, h, 2 * h).astype(np.float64)
        k, lab = P.auto_exposure(hdr), C.LABELS[P.label_of(name)]
        for d in range(a.draws):
            m = P.rotate_u(hdr, rng.integers(2 * h)) * k * 2.0 ** rng.uniform(-1.5, 1.5)
            alpha = np.ones((64, 128)) if d == 0 else masks[d - 1]
            alpha = np.repeat(np.repeat(alpha, h // 64, 0), h // 64, 1)           # [h, 2h]
            ldr = np.where(alpha[..., None] > 0.5, expose(m, 0.0), 0.0)
            lum = m @ LUMA
            for f in factors:
                lobes = L.predict_lobes(*L.downsample_clipped(ldr, alpha, f), head, lab)
                if not lobes:
                    continue
                pred = sum(lb["luminance_power"] for lb in lobes)
                true = sum(float((lum * dw * np.repeat(np.repeat(lb["region"], f, 0), f, 1)).sum())
                           for lb in lobes)
                errs[f].append((np.log(pred / max(true, 1e-300)), name))
    print(f"{len(names)} maps at {2 * h}x{h}, {a.draws} draws each, "
          f"{time.perf_counter() - t0:.0f} s\n")
    print("| head rows | draws with clipped light | mean abs log error | bias | "
          + " | ".join(names) + " |")
    print("|---" * (4 + len(names)) + "|")
    for f in factors:
        e = np.array([x[0] for x in errs[f]])
        per = [np.mean([x[0] for x in errs[f] if x[1] == n] or [np.nan]) for n in names]
        print(f"| {h // f} | {len(e)} | {np.abs(e).mean():.2f} | {e.mean():+.2f} | "
              + " | ".join(f"{v:+.2f}" for v in per) + " |")


if __name__ == "__main__":
    main()
