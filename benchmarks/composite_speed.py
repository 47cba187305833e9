"""Seconds per frame of the composite against image size, SOP against traced shadows.

Renders the first ``--frames`` cameras of a composition's test cameras with ``render-comp``
(``stages.render_comp``) at each ``--res`` for each variant, in one run (ratios: machines
are noisy), and prints s/frame (median after the first frame, which compiles kernels) and
the trace / SOP ratio. With ground truth at the composition's own size, its PSNR is printed
at that size only.

    python benchmarks/composite_speed.py --comp /tmp/demo/comp \
        --cameras /tmp/demo/dataset/comp/transforms_test.json --res 64 128 256 512
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--comp", type=Path, required=True, help="composition folder (compose --out)")
    ap.add_argument("--cameras", type=Path, required=True, help="NeRF-synthetic transforms json")
    ap.add_argument("--res", type=int, nargs="+", default=[64, 128, 256, 512])
    ap.add_argument("--variants", nargs="+", default=["sop", "trace"])
    ap.add_argument("--frames", type=int, default=2,
                    help="cameras rendered per size (1: the first frame's time, compilation "
                         "included)")
    ap.add_argument("--out", type=Path, default=None, help="write the table as JSON here")
    a = ap.parse_args(argv)
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.stages.render_comp import render_comp
    cams = json.loads(a.cameras.read_text())
    cams["frames"] = cams["frames"][:max(a.frames, 1)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cam_file = Path(tmp) / "cameras.json"
        cam_file.write_text(json.dumps(cams))
        print(f"{'res':>5} " + " ".join(f"{v + ' s/frame':>15}" for v in a.variants)
              + (f" {'trace/sop':>10}" if {"sop", "trace"} <= set(a.variants) else ""),
              flush=True)
        for res in a.res:
            t = {}
            for v in a.variants:
                m = render_comp(a.comp, cam_file, v, res=res, progress=False)
                t[v] = m["frame_seconds"]
            ratio = t["trace"] / t["sop"] if {"sop", "trace"} <= set(t) else None
            print(f"{res:5d} " + " ".join(f"{t[v]:15.2f}" for v in a.variants)
                  + (f" {ratio:10.1f}" if ratio else ""), flush=True)
            rows.append({"res": res, **{f"{v}_frame_seconds": t[v] for v in a.variants},
                         "trace_over_sop": ratio})
    if a.out:
        a.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
