"""Where a composite's shadow loses its darkness, term by term (issue: shadows too light).

For a composition dataset with path-traced truth (``make-dataset composition`` or the
demo's ``dataset/``: ``comp/gt/*.exr`` with the object, ``comp/empty/*.exr`` without,
``comp/mask/*.png`` the object's pixels) and a composition of it (``comgs compose``), the
shadow ratio S the renderer multiplies the scene by is read straight from the integrator
(no noshadow division) and compared, in the truth's shadow pixels (truth / empty < 0.7
in luminance, outside the object), with the truth's own ratio. Rows switch one term at a
time:

* light: ``true`` (the dataset's map path-traced at the placement, ``probes/<name>.exr``,
  written here when missing) or ``est`` (the composition's own map);
* visibility: ``trace`` (occlusion traced per shading ray) or ``sop`` (the cached probes);
* receivers' normals: ``depth`` (the default), ``depth:R`` (averaged over (2R+1)² pixels
  instead of the default's), ``surfel`` or ``flat`` (the ground's true (0, 0, 1): an
  oracle, only right on the ground);
* ``probe_k``: probes blended per point (SOP);
* ``sun_rays``: the composite's per-pixel shadow rays toward the dominant light (0: off);
* ``map``: (SOP) the sun rays look up a shadow map of this resolution (0: traced per
  pixel; ``comgs_composite`` ``sun_map_res``).

Columns: mean S in the truth's shadow pixels, the truth's mean ratio there, depth ratio
(1 − S) / (1 − truth) (1: as dark as the truth), and the IoU of the shadow masks.

    python benchmarks/shadow_terms.py --data /tmp/demo/dataset --comp /tmp/demo/comp \
        --out /tmp/shadow_terms
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

THRESH = 0.7                      # truth / empty below this: a shadow pixel of the truth


def lum(a):
    return a[..., 0] * 0.2126 + a[..., 1] * 0.7152 + a[..., 2] * 0.0722


def truth(data: Path, name: str):
    """(truth ratio [H, W], shadow mask [H, W], object mask [H, W]) of frame ``name``."""
    from comgs_dr.core.exr import read_image as read_exr
    from comgs_dr.data.images import read_image
    gt = read_exr(data / "comp" / "gt" / f"{name}.exr")[..., :3]
    em = read_exr(data / "comp" / "empty" / f"{name}.exr")[..., :3]
    obj = read_image(data / "comp" / "mask" / f"{name}.png")
    obj = (obj[..., 0] if obj.ndim == 3 else obj) > 0.5
    r = lum(gt) / np.maximum(lum(em), 1e-6)
    return r, (r < THRESH) & ~obj & (lum(em) > 1e-3), obj


def true_comp(data: Path, comp: Path, out: Path) -> Path:
    """The composition re-composed with the true map at the placement (``--env``)."""
    m = json.loads((comp / "composition.json").read_text())
    names = list(m["objects"])
    if len(names) != 1:
        raise SystemExit("shadow_terms: one object per composition (the true map is per object)")
    probe = data / "probes" / f"{names[0]}.exr"
    if not probe.is_file():
        from comgs_dr.data.placement_probe import write_probes
        write_probes(data)
    dst = out / "comp_true"
    if not (dst / "composition.json").is_file():
        cfg = m["config"]["shadow"]
        cmd = [sys.executable, "-m", "comgs_dr.cli", "compose", m["scene"]["run"],
               "--object", f"{names[0]}={m['objects'][names[0]]['run']}",
               "--placement", str(data / "transform.json"), "--env", str(probe),
               "--shadow-probes", str(cfg["count"]), "--out", str(dst), "--quiet"]
        if cfg["res"] == 16:
            cmd += ["--preset", "fast"]
        subprocess.run(cmd, check=True)
    return dst


def shadow_maps(comp: Path, cams, variant: str, normals: str, probe_k: int,
                sun_rays: int, sun_map: int = 512, seed: int = 0):
    """{frame: S luminance [H, W]} read from the integrator's shadow pass."""
    import drjit as dr
    import mitsuba as mi

    from comgs_dr.data import comp_folder
    from comgs_dr.stages.render_comp import load_comp_scene
    manifest = comp_folder.read_manifest(comp)
    flat = normals == "flat"
    radius = int(normals.split(":")[1]) if normals.startswith("depth:") else None
    extra = {"shadow_normals": "depth" if flat or radius else normals, "probe_k": probe_k,
             "sun_rays": sun_rays, "sun_map_res": sun_map}
    scene = load_comp_scene(comp, variant, None,
                            [comp_folder.sensor_dict(cams[0],
                                                     clip=comp_folder.clip_for(manifest, cams))],
                            **extra)
    integ, sensor = scene.integrator(), scene.sensors()[0]
    params = mi.traverse(sensor)
    out = {}
    for i, c in enumerate(cams):
        params["to_world"] = mi.ScalarTransform4f(np.asarray(c["to_world"]).tolist())
        params.update()
        st = integ._setup(scene)
        buf = integ._buffers(scene, sensor, st)
        if radius:
            dn = type(buf).depth_normals
            buf.depth_normals = lambda g, *a, _f=dn, _b=buf, **k: _f(_b, g, radius=radius)
        if flat:
            up = dr.full(mi.Vector3f, 0.0, dr.width(buf.weight[0]))
            up.z = 1.0
            buf.depth_normals = lambda g, *a, _u=up, **k: (_u, None)
        S = integ._shadow(buf, st, seed + i)
        h, w = buf.shape
        out[c["name"]] = lum(np.asarray(S, np.float32).T.reshape(h, w, 3)) if S is not None \
            else np.ones((h, w), np.float32)
    return out


def score(data: Path, maps: dict) -> dict:
    s_in, t_in, iou = [], [], []
    for name, S in maps.items():
        r, m, obj = truth(data, name)
        s_in.append(S[m])
        t_in.append(r[m])
        ours = (S < THRESH) & ~obj
        iou.append((ours & m).sum() / max((ours | m).sum(), 1))
    s, t = np.concatenate(s_in), np.concatenate(t_in)
    return {"S": float(s.mean()), "truth": float(t.mean()),
            "depth_ratio": float((1 - s.mean()) / max(1 - t.mean(), 1e-6)),
            "iou": float(np.mean(iou)), "pixels": int(len(s))}


ROWS = [  # (light, visibility, normals, probe_k, sun_rays, sun map res)
    ("true", "trace", "flat", 8, 0, 0),
    ("true", "trace", "depth", 8, 0, 0),
    ("true", "trace", "surfel", 8, 0, 0),
    ("true", "sop", "depth", 8, 0, 0),
    ("true", "sop", "depth", 1, 0, 0),
    ("est", "trace", "depth", 8, 0, 0),
    ("est", "sop", "depth", 8, 0, 0),
]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="composition dataset folder")
    ap.add_argument("--comp", type=Path, required=True, help="its composition (compose --out)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--sun-rays", type=int, nargs="*", default=[16],
                    help="extra rows: these per-pixel sun ray counts (both lights, sop and trace)")
    ap.add_argument("--rows", default="all", help="'all' or comma-separated row indices")
    ap.add_argument("--extra", nargs="*", default=[],
                    help="more rows as LIGHT,VIS,NORMALS,K,SUN[,MAP] (e.g. "
                         "true,sop,probes,8,16,512; MAP default 512)")
    a = ap.parse_args(argv)
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.data import comp_folder
    a.out.mkdir(parents=True, exist_ok=True)
    comps = {"est": a.comp, "true": true_comp(a.data, a.comp, a.out)}
    manifest = comp_folder.read_manifest(a.comp)
    cams = comp_folder.camera_source(a.data / "comp", manifest.get("world_from_source"))
    from comgs_dr.data.images import read_image
    for c in cams:
        h, w = read_image(a.data / "comp" / "gt" / f"{c['name']}.png").shape[:2]
        c["width"], c["height"] = w, h
    rows = ROWS + [(lt, vis, "depth", 8, n, 512) for n in a.sun_rays for lt in ("true", "est")
                   for vis in ("sop", "trace")]
    if a.rows != "all":
        rows = [rows[int(i)] for i in a.rows.split(",") if i]
    for e in a.extra:
        f = e.split(",")
        rows.append((f[0], f[1], f[2], int(f[3]), int(f[4]), int(f[5]) if len(f) > 5 else 512))
    print(f"{'light':5} {'vis':5} {'normals':7} {'k':>2} {'sun':>4} {'map':>4} {'S':>6} "
          f"{'truth':>6} {'depth':>6} {'IoU':>5} {'s':>5}")
    results = []
    for lt, vis, nrm, k, sun, smap in rows:
        t = time.perf_counter()
        sc = score(a.data, shadow_maps(comps[lt], cams, vis, nrm, k, sun, smap))
        dt = time.perf_counter() - t
        shown = smap if vis == "sop" and sun else "-"
        print(f"{lt:5} {vis:5} {nrm:7} {k:2d} {sun:4d} {shown:>4} {sc['S']:6.3f} "
              f"{sc['truth']:6.3f} {sc['depth_ratio']:6.3f} {sc['iou']:5.2f} {dt:5.1f}",
              flush=True)
        results.append({"light": lt, "visibility": vis, "normals": nrm, "probe_k": k,
                        "sun_rays": sun, "sun_map_res": smap, **sc, "seconds": dt})
    (a.out / "shadow_terms.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
