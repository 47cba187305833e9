"""Step 2's material priors side by side on finished step-1 object runs.

For each run (``--runs``: step-1 object runs whose dataset has the albedo AOV, as `comgs
make-dataset` writes it) and each variant (``--variants``: ``name:field=value,...`` of
``MaterialConfig``), step 2 is run from the same step-1 surfels into ``--work``, then its
test views are re-rendered under the capture's own map (``relight_run``) and scored:

* ``PSNR``: the test views under the capture light (the fit itself);
* ``albedo PSNR``: the albedo buffer against the true albedo AOV after per-channel scale
  alignment (``relight.align_albedo``: the light/albedo colour ambiguity removed, so this
  is the albedo's spatial accuracy — noise, texture, shading baked in);
* ``metal``: mean metallic of the opaque surfels (opacity > ½); ``rough IQR``: the spread of
  their roughness; ``nbr diff``: the mean material difference between neighbours on the
  step-1 colour-aware graph (``train.material_smoothness``, the quantity its prior
  penalises);
* ``s``: step 2's training time.

``env_file=capture`` in a variant stands for the run's own capture light (its dataset's
``meta.json`` map and scale): step 2 under a known light.

    python benchmarks/material_priors.py --runs RUN1,RUN2 --work /tmp/matpri
    python benchmarks/material_priors.py --runs RUN --variants "base:,smooth:lambda_smooth=0.1"
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_VARIANTS = "base:,smooth0.03:lambda_smooth=0.03,smooth0.1:lambda_smooth=0.1," \
                   "smooth0.3:lambda_smooth=0.3"


def parse_variants(text: str, cfg_cls) -> dict:
    """{name: {field: value}} from ``"a:f=v,g=w,b:,c:f=v"`` (comma-separated; ``name:``
    starts a variant, ``field=value`` items follow it; a value is read as JSON, else kept
    as a string; ``name:`` alone is the defaults)."""
    fields = {f.name: f for f in dataclasses.fields(cfg_cls)}
    out, cur = {}, None
    for tok in [t.strip() for t in text.split(",") if t.strip()]:
        if ":" in tok:
            cur, tok = tok.split(":", 1)
            cur = cur.strip()
            if not cur or cur in out:
                raise ValueError(f"--variants: empty or repeated name in {text!r}")
            out[cur] = {}
            if not tok.strip():
                continue
        if cur is None or "=" not in tok:
            raise ValueError(f"--variants: expected name:field=value, got {tok!r}")
        k, v = (s.strip() for s in tok.split("=", 1))
        if k not in fields:
            raise ValueError(f"--variants: {k!r} is not a MaterialConfig field")
        try:
            out[cur][k] = json.loads(v)
        except json.JSONDecodeError:
            out[cur][k] = v
    if not out:
        raise ValueError("--variants: no variant given")
    return out


def material_stats(ply) -> dict:
    import mitsuba as mi

    from comgs_dr.surfels import load_ply
    from comgs_dr.train.material_smoothness import material_smoothness, pairs_from_params
    q = load_ply(str(ply))
    d = q.to_numpy()
    op = 1.0 / (1.0 + np.exp(-d["opacity_logit"]))
    s = op > 0.5
    r = d["roughness"][s]
    i, j, w = pairs_from_params(q)
    nbr = material_smoothness(q.albedo, q.roughness, q.metallic, mi.UInt32(i), mi.UInt32(j),
                              mi.Float(w))
    return {"metal": float(d["metallic"][s].mean()) if s.any() else float("nan"),
            "rough_iqr": float(np.subtract(*np.percentile(r, [75, 25]))) if s.any() else float("nan"),
            "nbr_diff": float(nbr[0]) if len(w) else float("nan")}


def run_variant(run: Path, work: Path, overrides: dict, iterations: int, rays: int) -> dict:
    from comgs_dr.stages.decompose import MaterialConfig, train_material
    from comgs_dr.stages.relight import relight_run
    from comgs_dr.train.run import read_run_info
    work.mkdir(parents=True, exist_ok=True)
    for f in run.iterdir():                       # the step-1 state only, never its material/
        if f.is_file():
            shutil.copy(f, work / f.name)
    meta = json.loads((Path(read_run_info(work)["data"]) / "meta.json").read_text())
    if overrides.get("env_file") == "capture":              # the dataset's own light
        overrides = {**overrides, "env_file": meta["envmap"],
                     "env_scale": float(meta.get("envmap_scale", 1.0))}
    cfg = MaterialConfig(**{"iterations": iterations, "eval_every": iterations,
                            "eval_views": 2, **overrides})
    t0 = time.perf_counter()
    s = train_material(work, None, cfg, progress=False)
    dt = time.perf_counter() - t0
    r = relight_run(work, meta["envmap"], envmap_scale=float(meta.get("envmap_scale", 1.0)),
                    rays=rays, out_dir=work / "relight_capture", progress=False)
    return {"psnr": s["psnr_test"], "albedo_psnr": r.get("albedo_psnr", float("nan")),
            **material_stats(work / "material" / "point_cloud.ply"), "seconds": dt}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", required=True, help="comma-separated step-1 object runs")
    ap.add_argument("--variants", default=DEFAULT_VARIANTS)
    ap.add_argument("--work", type=Path, default=Path("/tmp/material_priors"))
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--rays", type=int, default=128, help="rays of the scoring renders")
    a = ap.parse_args(argv)
    import comgs_dr
    comgs_dr.set_variant("auto")
    from comgs_dr.stages.decompose import MaterialConfig
    variants = parse_variants(a.variants, MaterialConfig)
    runs = [Path(r) for r in a.runs.split(",") if r]
    for r in runs:
        if not (r / "point_cloud.ply").is_file():
            raise FileNotFoundError(f"{r}: no point_cloud.ply (a finished step-1 run?)")
    rows = {}
    for r in runs:
        for name, ov in variants.items():
            key = f"{r.name}/{name}"
            print(f"{key}: step 2 ({a.iterations} iterations) ...", flush=True)
            rows[key] = run_variant(r, a.work / r.name / name, ov, a.iterations, a.rays)
    cols = ("psnr", "albedo_psnr", "metal", "rough_iqr", "nbr_diff", "seconds")
    print("\n| run / variant | PSNR | albedo PSNR | metal | rough IQR | nbr diff | s |")
    print("|---|---|---|---|---|---|---|")
    for k, v in rows.items():
        print(f"| {k} | " + " | ".join(f"{v[c]:.3f}" if c != "seconds" else f"{v[c]:.0f}"
                                        for c in cols) + " |")
    (a.work / "material_priors.json").write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    try:
        main()
    except (FileNotFoundError, ValueError) as exc:
        sys.exit(f"material_priors: error: {exc}")
