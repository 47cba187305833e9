"""Mesh export of a *trained* step-1 run: a sphere, watertight, Chamfer against the true one.

Renders a sphere dataset (icosphere of radius 0.8, uniform orange, procedural sky, training
views all around at elevations −80…80°), runs ``comgs reconstruct --object``, exports the
mesh with each method and prints, per method: watertight, Chamfer distance / radius (one
sides, ``sphere_error``, also used by ``tests/test_export_mesh.py``), faces, seconds; and the
distance of the surfel centres from the true sphere (why Poisson on centres shrinks).

    python benchmarks/mesh_sphere.py --out /tmp/sphere [--views 48] [--res 128] [--iterations 3000]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def sphere_error(mesh, centre, radius, n=20000) -> float:
    """Symmetric Chamfer distance between a trimesh and a sphere, over the radius: the mean
    of (mesh points' |distance to the sphere|) and (sphere points' distance to the mesh's
    sampled points, ≥ the distance to its surface)."""
    from scipy.spatial import cKDTree
    pts = mesh.sample(n)
    a = np.abs(np.linalg.norm(pts - centre, axis=1) - radius).mean()
    s = np.random.default_rng(0).normal(size=(4000, 3))
    s = centre + radius * s / np.linalg.norm(s, axis=1, keepdims=True)
    b = cKDTree(mesh.sample(5 * n)).query(s)[0].mean()
    return float((a + b) / 2 / radius)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--mesh-resolution", type=int, default=192)
    a = ap.parse_args(argv)
    import trimesh

    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.data.procedural import procedural_sky
    from comgs_dr.data.synthetic import ObjectDatasetConfig, make_object_dataset
    from comgs_dr.surfels import load_ply
    root = a.out
    root.mkdir(parents=True, exist_ok=True)
    ds, run = root / "ds", root / "run"
    if not (ds / "meta.json").is_file():
        trimesh.creation.icosphere(subdivisions=5, radius=0.8).export(root / "sphere.ply")
        sky = procedural_sky(root / "sky.exr", width=64)
        make_object_dataset(ObjectDatasetConfig(
            mesh=root / "sphere.ply", envmap=sky, out_dir=ds, n_train=a.views, n_test=8,
            resolution=a.res, spp=32, spp_aov=4, relight_envmaps=(),
            train_elevation_deg=(-80.0, 80.0), up_axis="z", texture=None,
            base_color=(0.7, 0.4, 0.2)), progress=True)
    comgs = [sys.executable, "-m", "comgs_dr.cli"]
    if not (run / "point_cloud.ply").is_file():
        subprocess.run(comgs + ["reconstruct", str(ds), "--out", str(run), "--object",
                                "--iterations", str(a.iterations), "--quiet"], check=True)
    meta = json.loads((ds / "meta.json").read_text())
    tm = trimesh.load(root / "sphere.ply", force="mesh")
    tm.apply_transform(np.asarray(meta["object"]["object_to_world"]))
    centre = tm.vertices.mean(0)
    radius = float(np.linalg.norm(tm.vertices - centre, axis=1).mean())
    test = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()
            if "psnr_test" in line]
    print(f"step 1: {a.views} views at {a.res} px, {a.iterations} iterations, test PSNR "
          f"{test[-1]['psnr_test']:.2f} dB in {test[-1]['time_s']:.0f} s\n")
    print("| method | watertight | Chamfer / radius | faces | s |\n|---|---|---|---|---|")
    for method in ("tsdf", "poisson"):
        out = root / f"{method}.ply"
        t0 = time.perf_counter()
        subprocess.run(comgs + ["export-mesh", str(run), "--out", str(out), "--method", method,
                                "--resolution", str(a.mesh_resolution), "--quiet"], check=True)
        m = trimesh.load(out, force="mesh")
        print(f"| {method} | {m.is_watertight} | {100 * sphere_error(m, centre, radius):.2f} % | "
              f"{len(m.faces)} | {time.perf_counter() - t0:.1f} |")
    p = load_ply(run / "point_cloud.ply").to_numpy()
    op = 1.0 / (1.0 + np.exp(-p["opacity_logit"].astype(np.float64)))
    d = np.linalg.norm(p["means"] - centre, axis=1)[op > 0.2] / radius
    print(f"\nsurfel centres (opacity > 0.2): median distance from the centre {np.median(d):.4f} "
          f"of the radius (the rendered surface is the composite in front of them)")


if __name__ == "__main__":
    main()
