"""Which clipped region holds the strongest light? Ranking of the regions by each predictor.

The dominant-light angle of ``lighting_eval`` (light visible) is decided by one choice: which of
the panorama's clipped regions (``lights.clipped_regions``) gets the most power. This benchmark
isolates that choice. For each map (default: the held-out shared maps, ``pano_data.HELD_OUT``)
and ``--masks`` traced surfel masks (the same protocol as ``lighting_eval``: 128×256, random
rotation about Z, auto exposure, masks below 40 % coverage skipped), the EV-0 LDR panorama is
read and every observed clipped region is given a power by each predictor:

* ``seen``: its EV-0 pixels (what a fill keeps; the baselines' choice);
* ``head``: the light head (``lights.predict_lobes``);
* ``net``: the completion net's fused EV 0/−2.5/−5 brackets (``hdr.fuse_brackets``) there;
* ``geo a``: head^(1−a) · net^a, the two combined in log space (a = ¼, ½, ¾);
* ``rel a``: the head's power times (g_net / its geometric mean over the panorama's
  regions)^a, g_net = net / seen: the net's gains trusted only relative to each other
  (its brackets cannot exceed 32× the white level, so their absolute scale is capped);
* ``share a``: the head's total power shared ∝ head^(1−a) · net^a (ranks as ``geo a``):
  ``lights.add_lights(trust_brackets=a)``, what ``estimate-light`` does.

Per predictor: top-1 (the region it gives the most power holds the most true power), over
panoramas with ≥ 2 regions, and over those whose strongest region has ≥ 1.5× the next; the
mean |log(predicted / true power)| over all regions; top-1 per map (margin 1.5).

``--nested``: every map, held out or not, and the vote's weight a of ``share a`` chosen
leave-one-map-out from ``NESTED_GRID`` (top-1 on the other maps, ties broken by their log
error), then scored on the map left out: what choosing a costs when no map is looked at twice.

``--cv-heads CV`` (``train-light-head --cv-out CV``): every map is scored with ``CV/<stem>.pt``,
the head fitted without it (as ``lighting_eval --cv-heads``).

    python benchmarks/light_ranking.py [--maps DIR] [--masks 16] [--seed 0] [--train-maps]
                                       [--light-head H | --cv-heads CV]
    python benchmarks/light_ranking.py --nested
"""
from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

MARGINS = (1.0, 1.5)
MIX = (0.25, 0.5, 0.75)
REL = (0.5, 1.0)
SHARE = (0.25, 0.5)
NESTED_GRID = (0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 1.0)


def region_powers(maps, masks: int, seed: int, res: int = 128, progress=print,
                  head_path=None, cv_heads: dict | None = None) -> list[dict]:
    """[{map, regions: [{true, seen, head, net}]}] for panoramas (``res`` × 2·``res``) with
    ≥ 2 clipped regions (luminance powers, EV-0 radiance units); ``head_path``: light-head
    weights (None: the shipped head, or for a held-out map its fold without that map,
    ``cv_heads.held_out_head``); ``cv_heads``: {map stem: weights} used first."""
    import torch

    from comgs_dr.core.colorspace import LUMA
    from comgs_dr.core.equirect import pixel_solid_angles
    from comgs_dr.data import pano_masks
    from comgs_dr.lighting import backends as B
    from comgs_dr.lighting import completion as C
    from comgs_dr.lighting import hdr
    from comgs_dr.lighting import lights as L
    from comgs_dr.lighting import pano_data as P
    from cv_heads import held_out_head
    from lighting_eval import load_eval_map
    torch.set_num_threads(1)
    net = B.load_network_backend()
    fixed = None if head_path in (None, "default") else L.load_head(head_path)
    h, w = res, 2 * res
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    bank = pano_masks.mask_bank(masks * len(maps), h, w, seed)
    rng = np.random.default_rng(seed)
    rows = []
    for i, path in enumerate(maps):
        gm, lab = load_eval_map(path, h), C.LABELS[P.label_of(path.stem)]
        # the shipped head saw every shared map: a held-out map gets its fold without it
        head = fixed if fixed is not None else L.load_head(
            (cv_heads or {}).get(path.stem) or held_out_head(path.stem))
        for j in range(masks):
            mk, shift = bank[i * masks + j], int(rng.integers(w))
            if mk["coverage"] < 0.4:
                continue
            gt = np.roll(gm, shift, 1)
            gt = gt * P.auto_exposure(gt)                                         # [H, W, 3]
            alpha = np.clip(np.asarray(mk["alpha"], np.float64), 0.0, 1.0)       # [H, W]
            rgb = np.where(alpha[..., None] > 0, hdr.expose(gt, 0.0), 0.0).astype(np.float32)
            lobes = L.predict_lobes(rgb, alpha, head, lab)
            if len(lobes) < 2:
                continue
            ldrs = net.complete(rgb, np.asarray(mk["normal"], np.float32),
                                alpha.astype(np.float32), evs=C.DEFAULT_EVS, label=lab)
            fused = np.asarray(hdr.fuse_brackets(ldrs, C.DEFAULT_EVS), np.float64) @ LUMA
            lum = gt @ LUMA
            rows.append({"map": path.stem, "regions": [
                {"true": float((lum * dw * lb["region"]).sum()),
                 "seen": lb["luminance_power"] / lb["gain"], "head": lb["luminance_power"],
                 "net": float((fused * dw * lb["region"]).sum())} for lb in lobes]})
        progress(f"{path.stem}: {len(rows)} panoramas with >= 2 clipped regions so far")
    return rows


def predictors() -> dict:
    """{name: f(regions) -> [R] predicted powers} of one panorama's regions."""
    def key(k):
        return lambda regs: np.array([r[k] for r in regs])

    def geo(a):
        return lambda regs: np.array([r["head"] ** (1 - a) * max(r["net"], 1e-12) ** a
                                      for r in regs])

    def rel(a):
        def f(regs):
            lg = np.log([max(r["net"], 1e-12) / max(r["seen"], 1e-12) for r in regs])
            return np.array([r["head"] for r in regs]) * np.exp(a * (lg - lg.mean()))
        return f

    out = {k: key(k) for k in ("seen", "head", "net")}
    return (out | {f"geo {a:g}": geo(a) for a in MIX} | {f"rel {a:g}": rel(a) for a in REL}
            | {f"share {a:g}": share_power(a) for a in SHARE})


def share_power(a: float):
    """``lights.shared_power`` on benchmark rows (``lights.vote_shares``): the head's total
    shared ∝ head^(1−a)·net^a."""
    from comgs_dr.lighting.lights import vote_shares
    return lambda regs: vote_shares([r["head"] for r in regs], [r["net"] for r in regs], a)


def nested_choice(rows: list[dict], grid=NESTED_GRID, fixed=(0.0, 0.25)) -> dict:
    """Leave-one-map-out choice of ``share a``: {map: a chosen on the other maps} and
    {"nested" | "a=<x>": [hits, panoramas]} summed over the maps left out (margin 1). Ties
    in top-1 and log error go to the smallest a (the first in ``grid``)."""
    maps = sorted({r["map"] for r in rows})
    if len(maps) < 2:
        raise ValueError(f"nested_choice: need rows of at least two maps, got {maps}")
    chosen, tot = {}, {k: [0, 0] for k in ["nested"] + [f"a={x:g}" for x in fixed]}
    for m in maps:
        rest, held = [r for r in rows if r["map"] != m], [r for r in rows if r["map"] == m]
        chosen[m] = max(grid, key=lambda a: (score(rest, share_power(a), 1.0)[0],
                                             -log_error(rest, share_power(a))))
        for k, a in [("nested", chosen[m])] + [(f"a={x:g}", x) for x in fixed]:
            _, n, per = score(held, share_power(a), 1.0)
            tot[k][0] += per.get(m, [0, 0])[0]
            tot[k][1] += n
    return {"chosen": chosen, "hits": tot}


def score(rows: list[dict], f, margin: float) -> tuple[float, int, dict]:
    """(top-1 rate, panoramas counted, {map: [hits, n]}) over panoramas whose strongest
    region has ≥ ``margin``× the true power of the next."""
    hit, n, per = 0, 0, defaultdict(lambda: [0, 0])
    for row in rows:
        t = np.array([r["true"] for r in row["regions"]])
        s = np.sort(t)[::-1]
        if s[0] < margin * s[1]:
            continue
        ok = int(np.argmax(f(row["regions"])) == np.argmax(t))
        hit, n = hit + ok, n + 1
        per[row["map"]][0] += ok
        per[row["map"]][1] += 1
    return hit / max(n, 1), n, dict(per)


def log_error(rows: list[dict], f) -> float:
    """Mean |log(predicted / true power)| over every region of every panorama."""
    return float(np.mean([abs(np.log(max(v, 1e-12) / max(r["true"], 1e-12)))
                          for row in rows for r, v in zip(row["regions"], f(row["regions"]))]))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--maps", default=None, help="folder of maps (default: shared/data/hdri)")
    ap.add_argument("--masks", type=int, default=16, help="masks per map (>= 1)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="dump the per-region powers here")
    ap.add_argument("--train-maps", action="store_true", help="the maps the net and head "
                    "trained on (in sample) instead of pano_data.HELD_OUT")
    ap.add_argument("--light-head", default=None, help="light-head weights (default: the "
                    "shipped head)")
    ap.add_argument("--cv-heads", default=None, help="folder of cross-validation light heads "
                    "(train-light-head --cv-out): each map scored with <stem>.pt")
    ap.add_argument("--nested", action="store_true", help="every map, and the vote's weight "
                    "chosen leave-one-map-out (see the module docstring)")
    a = ap.parse_args(argv)
    if a.masks < 1:
        raise SystemExit("--masks must be >= 1")
    if a.nested and a.train_maps:
        raise SystemExit("--nested takes every map; leave out --train-maps")
    if a.cv_heads is not None and a.light_head is not None:
        raise SystemExit("--cv-heads replaces --light-head; give one of them")
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.data.synthetic import shared_data_dir
    from comgs_dr.lighting import pano_data as P
    from lighting_eval import cv_head_paths, list_maps
    maps = [p for p in list_maps(a.maps or shared_data_dir() / "hdri")
            if a.nested or (p.stem in P.HELD_OUT) != a.train_maps]
    if not maps:
        raise SystemExit("no map left to evaluate")
    cv = cv_head_paths(a, maps) if a.cv_heads is not None else None   # before any work
    t0 = time.perf_counter()
    rows = region_powers(maps, a.masks, a.seed, head_path=a.light_head, cv_heads=cv)
    if a.json:
        Path(a.json).write_text(json.dumps(rows))
    names = sorted({r["map"] for r in rows})
    if a.nested:
        res = nested_choice(rows)
        print(f"\nleave-one-map-out choice of the vote's weight over {len(names)} maps "
              f"({time.perf_counter() - t0:.0f} s)\n\n| map left out | a chosen on the "
              "others |\n|---|---|")
        for m, x in res["chosen"].items():
            print(f"| {m} | {x:g} |")
        print("\n| rule | top-1 on the maps left out |\n|---|---|")
        for k, (h, n) in res["hits"].items():
            print(f"| {k} | {h}/{n} = {h / max(n, 1):.3f} |")
        return res
    print(f"\n{len(rows)} panoramas with >= 2 clipped regions, {len(maps)} maps, "
          f"{time.perf_counter() - t0:.0f} s; per map: top-1 hits / panoramas at margin "
          f"{MARGINS[1]:g}\n")
    print(f"| predictor | top-1 | top-1, margin {MARGINS[1]:g} | mean abs log error | "
          + " | ".join(names) + " |")
    print("|---|---|---|---|" + "---|" * len(names))
    for name, f in predictors().items():
        (a1, n1, _), (a2, n2, per) = (score(rows, f, m) for m in MARGINS)
        cells = [f"{per[m][0]}/{per[m][1]}" if m in per else "-" for m in names]
        print(f"| {name} | {a1:.3f} ({n1}) | {a2:.3f} ({n2}) | {log_error(rows, f):.3f} | "
              + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
