"""Tables and figures of ``lighting_eval.py`` (its records in, text and PNGs out).

Split from the evaluation so that each stays readable: ``lighting_eval`` draws the samples
and scores them; this module pools the records per method, coverage group, material and
dominant-light split (``summarise``), prints the tables, bootstraps the angle ratio over maps
(``angle_ratio_ci``) and draws the example and per-map figures. Constants shared by both
live here.
"""
from __future__ import annotations

import os
import platform
from pathlib import Path

import numpy as np

GROUPS = (("40-60", 0.4, 0.6), ("60-80", 0.6, 0.8), ("80-100", 0.8, 1.0 + 1e-9))
METRICS = (("si_rmse", "si-RMSE"), ("angular_deg", "angular °"), ("nrmse", "nRMSE"))
BASELINES = ("mean", "push_pull", "sh", "diffusers")
EXTRA = (("light_angle_deg", "light angle °"), ("relight_psnr", "relight PSNR"),
         ("sun_up_log_err", "|log E_sun/E_up err|"))
SPLITS = ("all", "visible", "hole", "clear")
CLEAR_MARGIN = 1.5      # fixed before measuring: P(dominant) / P(second) for a "clear" light
CLEAR_SEEDS = 0.99      # the lights compared for "clear": seeds in the top 1 % of the sphere
CLEAR_SAME_DEG = 10.0   # ... whose strongest must be the dominant light (within this angle)


def ours(methods) -> str | None:
    """The default pipeline of ``estimate-light`` where it was evaluated."""
    for name in ("net+sh+lights", "net+sh", "net+lights", "net"):
        if name in methods:
            return name
    return None


# ---------------------------------------------------------------------------------------
# Tables

def _mean(xs):
    return float(np.mean(xs)) if len(xs) else float("nan")


def _median(xs):
    return float(np.median(xs)) if len(xs) else float("nan")


def _split(recs, split: str):
    if split == "all":
        return recs
    if split == "clear":
        return [r for r in recs if r["light_in_hole"] is False and r["light_clear"]]
    return [r for r in recs if r["light_in_hole"] is (split == "hole")]


def _stats(rs) -> dict:
    out = {k: _mean([r[k] for r in rs]) for k, _ in METRICS}
    for k, _ in EXTRA:
        out[k] = _mean([r[k] for r in rs if r[k] is not None])
    out["pano_si_rmse"] = _mean([r["pano_si_rmse"] for r in rs])
    out["si_rmse_median"] = _median([r["si_rmse"] for r in rs])
    out["n"] = len(rs)
    return out


def values_by_map(records, method: str, key: str, split: str = "all") -> dict:
    """{map: [r[key] of ``method``'s ``split`` samples, None left out]}."""
    out = {}
    for r in _split([r for r in records if r["method"] == method], split):
        if r[key] is not None:
            out.setdefault(r["map"], []).append(float(r[key]))
    return out


def angle_ratio_ci(records, ours: str, base: str, split: str = "visible",
                   n_boot: int = 2000, level: float = 0.9, seed: int = 0) -> dict:
    """Mean dominant-light angle of ``ours`` over ``base`` on the ``split`` samples, with a
    ``level`` bootstrap interval that resamples whole maps (a map's samples share its
    lights, so samples are not independent; with 5 maps the interval is wide, honestly).
    {ratio, lo, hi, maps}; NaNs when there is nothing to compare."""
    a = values_by_map(records, ours, "light_angle_deg", split)
    b = values_by_map(records, base, "light_angle_deg", split)
    maps = sorted(set(a) & set(b))
    nan = {"ratio": float("nan"), "lo": float("nan"), "hi": float("nan"), "maps": len(maps)}
    if not maps:
        return nan
    sa = np.array([sum(a[m]) for m in maps])                                    # [M]
    sb = np.array([sum(b[m]) for m in maps])                                    # [M]
    na = np.array([len(a[m]) for m in maps])
    nb = np.array([len(b[m]) for m in maps])
    if sb.sum() <= 0:
        return nan
    ratio = float((sa.sum() / na.sum()) / (sb.sum() / nb.sum()))
    idx = np.random.default_rng(seed).integers(len(maps), size=(n_boot, len(maps)))
    num, den = sa[idx].sum(1) / na[idx].sum(1), sb[idx].sum(1) / nb[idx].sum(1)
    boot = num[den > 0] / den[den > 0]
    lo, hi = np.quantile(boot, [(1 - level) / 2, (1 + level) / 2])
    return {"ratio": ratio, "lo": float(lo), "hi": float(hi), "maps": len(maps)}


def summarise(res: dict) -> dict:
    recs, methods = res["records"], res["methods"]
    groups = [g for g, _, _ in GROUPS]
    per_mat, per_group, per_split, overall, timing = {}, {}, {}, {}, {}
    for me in methods:
        rm = [r for r in recs if r["method"] == me]
        timing[me] = {"mean_s": _mean([r["time_s"] for r in rm]),
                      "median_s": _median([r["time_s"] for r in rm])}
        overall[me] = _stats(rm)
        for sp in SPLITS[1:]:
            per_split[(me, "all", sp)] = _stats(_split(rm, sp))
        for g in groups:
            rg = [r for r in rm if r["group"] == g]
            per_group[(me, g)] = _stats(rg)
            for sp in SPLITS[1:]:
                per_split[(me, g, sp)] = _stats(_split(rg, sp))
            for mat in ("mirror", "matte_silver", "diffuse"):
                per_mat[(me, g, mat)] = {k: _mean([r["materials"][mat][k] for r in rg])
                                         for k, _ in METRICS}
    wins, n = 0, 0
    me_ours = ours(methods)
    base = [b for b in methods if b in BASELINES]
    if me_ours and base:
        for g in groups:
            if per_group[(me_ours, g)]["n"] == 0:
                continue
            for k in ("si_rmse", "angular_deg"):
                n += 1
                wins += all(per_group[(me_ours, g)][k] < per_group[(b, g)][k] for b in base)
    best = min(base, key=lambda b: overall[b]["si_rmse"]
               if np.isfinite(overall[b]["si_rmse"]) else np.inf) if base else None
    vis = {me: per_split[(me, "all", "visible")]["light_angle_deg"] for me in methods}
    best_vis = min((b for b in base if np.isfinite(vis[b])), key=lambda b: vis[b], default=None)
    clr = {me: per_split[(me, "all", "clear")]["light_angle_deg"] for me in methods}
    best_clr = min((b for b in base if np.isfinite(clr[b])), key=lambda b: clr[b], default=None)
    return {"per_material": per_mat, "per_group": per_group, "per_split": per_split,
            "overall": overall, "timing": timing, "net_wins": wins, "n_comparisons": n,
            "ours": me_ours, "best_baseline": best,
            "si_rmse_net": overall.get(me_ours, {}).get("si_rmse", float("nan")),
            "si_rmse_best_baseline": overall[best]["si_rmse"] if best else float("nan"),
            "light_angle_visible_ours": vis.get(me_ours, float("nan")),
            "light_angle_visible_best_baseline": vis[best_vis] if best_vis else float("nan"),
            "best_baseline_light_angle": best_vis,
            "light_angle_clear_ours": clr.get(me_ours, float("nan")),
            "light_angle_clear_best_baseline": clr[best_clr] if best_clr else float("nan"),
            "best_baseline_light_angle_clear": best_clr,
            "n_clear": per_split[(me_ours, "all", "clear")]["n"] if me_ours else 0,
            "light_angle_visible_ratio": angle_ratio_ci(recs, me_ours, best_vis)
            if me_ours and best_vis else None,
            "light_angle_clear_ratio": angle_ratio_ci(recs, me_ours, best_clr, "clear")
            if me_ours and best_clr else None}


def label_counts(records) -> dict:
    """{map: {label: samples}} of the labels the models were given (one record per sample:
    the first method's), for maps where any label was "auto"."""
    out, first = {}, None
    for r in records:
        first = first or r["method"]
        if r["method"] == first and r.get("label_requested") == "auto":
            c = out.setdefault(r["map"], {})
            c[r["label"]] = c.get(r["label"], 0) + 1
    return out


def print_label_table(records) -> None:
    """What ``--label auto`` answered, per map (nothing when no label was auto)."""
    counts = label_counts(records)
    if not counts:
        return
    print("\n### Labels given by the classifier (`auto`, samples per map)\n\n"
          "| map | outdoor | indoor | unknown |\n|---|---|---|---|")
    for m, c in counts.items():
        print(f"| {m} | {c.get('outdoor', 0)} | {c.get('indoor', 0)} | {c.get('unknown', 0)} |")


def dominance_table(records, method: str) -> list[dict]:
    """The near-tie warning against the error it warns of: ``method``'s samples whose true
    dominant light is observed, split by ``light_dominance`` (fewer than two clipped regions;
    below ``lights.DOMINANCE_MARGIN``, where estimate-light warns; at or above it): samples,
    mean light angle, and the share more than 30° off."""
    from comgs_dr.lighting.lights import DOMINANCE_MARGIN
    rows = {"< 2 clipped regions": [], f"near tie (< {DOMINANCE_MARGIN:g}, warned)": [],
            f">= {DOMINANCE_MARGIN:g}": []}
    keys = list(rows)
    for r in records:
        if r["method"] != method or r["light_in_hole"] or r.get("light_angle_deg") is None:
            continue
        d = r.get("light_dominance")
        k = keys[0] if d is None else keys[1] if d < DOMINANCE_MARGIN else keys[2]
        rows[k].append(r["light_angle_deg"])
    return [{"split": k, "n": len(v), "light_angle": float(np.mean(v)) if v else float("nan"),
             "over_30": float(np.mean(np.asarray(v) > 30.0)) if v else float("nan")}
            for k, v in rows.items()]


def print_dominance_table(records, method: str) -> None:
    rows = dominance_table(records, method)
    if not any(r["n"] for r in rows) or method is None:
        return
    print(f"\n### The near-tie warning (`{method}`, true light visible)\n\n"
          "| strongest / next clipped region | n | light angle ° | share > 30° off |\n"
          "|---|---|---|---|")
    for r in rows:
        print(f"| {r['split']} | {r['n']} | {r['light_angle']:.1f} | {r['over_30']:.2f} |")


def print_tables(res: dict, s: dict, args):
    methods, groups = res["methods"], [g for g, _, _ in GROUPS]
    print(f"\nmachine: {platform.machine()} {platform.processor() or ''}, {os.cpu_count()} "
          f"cores, python {platform.python_version()}; maps {len(res['maps'])}, masks/map "
          f"{args.masks}, eval {args.res}x{2 * args.res}, spheres {args.sphere_size}² x 4 "
          f"azimuths, quadrature {args.quad}x{2 * args.quad}")
    print(f"samples kept {len(res['records']) // max(len(methods), 1)}, masks < 40 % skipped "
          f"{res['skipped']} of {res['n_bank']}; ours = {s['ours']}\n")
    print("### Per method x coverage group x material (means)\n")
    print("| method | coverage | material | n | " + " | ".join(h for _, h in METRICS) + " |")
    print("|---|---|---|---|" + "---|" * len(METRICS))
    for me in methods:
        for g in groups:
            n = s["per_group"][(me, g)]["n"]
            if not n:
                continue
            for mat in ("mirror", "matte_silver", "diffuse"):
                v = s["per_material"][(me, g, mat)]
                print(f"| {me} | {g} % | {mat} | {n} | "
                      + " | ".join(f"{v[k]:.4f}" for k, _ in METRICS) + " |")
    print("\n### Per coverage group and dominant-light split (sphere metrics averaged over "
          "the 3 materials; light angle, relighting PSNR and sun/up error of the dominant "
          "light; 'visible' = the true dominant light is observed, 'hole' = it is not, "
          f"'clear' = visible and the strongest light, ≥ {CLEAR_MARGIN}× the power of any "
          "other or the only one)\n")
    cols = METRICS + EXTRA
    print("| coverage | light | method | n | " + " | ".join(h for _, h in cols)
          + " | median si-RMSE | pano si-RMSE |")
    print("|---|---|---|---|" + "---|" * (len(cols) + 2))
    for g in groups + ["all"]:
        for sp in SPLITS:
            for me in methods:
                if sp == "all":
                    v = s["overall"][me] if g == "all" else s["per_group"][(me, g)]
                else:
                    v = s["per_split"][(me, g, sp)]
                if not v["n"]:
                    continue
                print(f"| {g} | {sp} | {me} | {v['n']} | "
                      + " | ".join(f"{v[k]:.4f}" for k, _ in cols)
                      + f" | {v['si_rmse_median']:.4f} | {v['pano_si_rmse']:.4f} |")
    print("\n### Time per sample (complete 3 EVs + fuse [+ light head]; sphere renders "
          f"{res['t_render']:.3f} s per sample; mask bank {res['t_masks']:.1f} s)\n")
    print("| method | mean s | median s |\n|---|---|---|")
    for me in methods:
        t = s["timing"][me]
        print(f"| {me} | {t['mean_s']:.4f} | {t['median_s']:.4f} |")


# ---------------------------------------------------------------------------------------
# Figure

def _tm(x):
    from comgs_dr.lighting.hdr import expose
    return np.clip(expose(np.maximum(np.asarray(x, np.float64), 0.0), 0.0), 0, 1)


def _sphere_strip(renders, mask):
    """View 0 of each material side by side, tonemapped, white background."""
    tiles = []
    for mat in ("mirror", "matte_silver", "diffuse"):
        t = _tm(renders[mat][0])
        tiles.append(np.where(mask[..., None], t, 1.0))
    return np.concatenate(tiles, 1)


def save_figure(res: dict, path: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ex, methods = res["examples"], res["methods"]
    if not ex:
        return None
    cols = 2 + len(methods)
    fig, axes = plt.subplots(2 * len(ex), cols, figsize=(2.6 * cols, 2.6 * len(ex)),
                             squeeze=False)
    for i, e in enumerate(ex):
        top, bot = axes[2 * i], axes[2 * i + 1]
        top[0].imshow(_tm(e["gt"]))
        top[0].set_title(f"GT {e['map']}", fontsize=7)
        top[1].imshow(np.where(e["alpha"][..., None] > 0.5, e["input"], [1.0, 0.0, 1.0]))
        top[1].set_title(f"input, coverage {100 * e['coverage']:.0f} %", fontsize=7)
        bot[0].imshow(_sphere_strip(e["gt_spheres"], e["mask"]))
        bot[1].axis("off")
        for k, me in enumerate(methods):
            est, est_r = e["est"][me]
            top[2 + k].imshow(_tm(est))
            top[2 + k].set_title(me, fontsize=7)
            bot[2 + k].imshow(_sphere_strip(est_r, e["mask"]))
        for ax in (*top, *bot):
            ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def save_map_figure(records, s: dict, path: Path):
    """Per map, ours vs the best baseline (by visible-light angle): the dominant-light angle
    with the light visible (bars, sample counts on top) and the relighting PSNR; the title
    gives the pooled ratio and its bootstrap interval over maps. None without both methods."""
    ours, base = s["ours"], s["best_baseline_light_angle"]
    if not ours or not base:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    maps = sorted({r["map"] for r in records})

    def per_map(me, key, split):                    # [(mean, count)] in ``maps`` order
        v = values_by_map(records, me, key, split)
        return [(float(np.mean(v[m])), len(v[m])) if m in v else (np.nan, 0) for m in maps]
    fig, axes = plt.subplots(1, 2, figsize=(max(6.0, 1.6 * len(maps) + 2), 3.4))
    x = np.arange(len(maps))
    for ax, key, split, label in ((axes[0], "light_angle_deg", "visible",
                                   "dominant-light angle, light visible (°)"),
                                  (axes[1], "relight_psnr", "all", "relighting PSNR (dB)")):
        for k, (me, col) in enumerate(((ours, "tab:orange"), (base, "tab:grey"))):
            vals = per_map(me, key, split)
            ax.bar(x + (k - 0.5) * 0.38, [v for v, _ in vals], 0.38, color=col, label=me)
            if split == "visible":
                for xi, (v, n) in zip(x + (k - 0.5) * 0.38, vals):
                    if np.isfinite(v):
                        ax.text(xi, v, str(n), ha="center", va="bottom", fontsize=6)
        ax.set_xticks(x, [m[:18] for m in maps], rotation=30, ha="right", fontsize=7)
        ax.set_ylabel(label, fontsize=8)
        ax.legend(fontsize=7)
    ci = s.get("light_angle_visible_ratio") or {}
    if ci and np.isfinite(ci.get("ratio", np.nan)):
        axes[0].set_title(f"ours / {base}: {ci['ratio']:.2f} "
                          f"(90 % over maps {ci['lo']:.2f}–{ci['hi']:.2f})", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _jsonable(s: dict) -> dict:
    return {k: ({"|".join(kk) if isinstance(kk, tuple) else kk: vv for kk, vv in v.items()}
                if isinstance(v, dict) else v) for k, v in s.items()}
