"""Benchmark: SOP fixed-radius KNN (sops.query, Dr.Jit) vs scipy cKDTree.

    python benchmarks/sop_query.py [--points 65536] [--probes 5000] [--k 8] [--repeat 5]

Two scenes: probes and points near a unit sphere's surface (the SOP use case), and
uniform in a cube. The radius is chosen so that ~``--neighbours`` probes are in range.
Columns: median wall time (warm: the first call, which compiles the kernel, is reported
separately), cKDTree = ``query(k, distance_upper_bound=radius)`` on the prebuilt tree
(neighbours only, no weights, no fallback), cKDTree+w = that plus the weights in numpy.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def sphere_points(rng, n, jitter):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return (v * (1.0 + rng.uniform(-jitter, jitter, (n, 1)))).astype(np.float32), v


def numpy_weights(probes, pts, nrm, idx, dist, radius):
    used = np.isfinite(dist)
    safe = np.where(used, idx, 0)
    d = probes[safe] - pts[:, None, :]
    length = np.maximum(np.where(used, dist, 1.0), 1e-6 * radius)
    w = (1 / length) * (0.5 * (1 + (d * nrm[:, None, :]).sum(-1) / length) + 0.01)
    w = np.where(used, w, 0)
    return w / np.maximum(w.sum(1, keepdims=True), 1e-30)


def timed(fn, repeat):
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=65536)
    ap.add_argument("--probes", type=int, default=5000)
    ap.add_argument("--k", type=int, default=8)
    ap.add_argument("--neighbours", type=float, default=12.0)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()

    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    import drjit as dr
    import mitsuba as mi
    from scipy.spatial import cKDTree

    from comgs_dr.core.hostarray import to_jit
    from comgs_dr.sops.query import ProbeGrid, query

    rng = np.random.default_rng(0)
    N, P, k = args.points, args.probes, args.k
    scenes = {}
    probes, _ = sphere_points(rng, P, 0.02)
    pts, nrm = sphere_points(rng, N, 0.0)
    # ~neighbours probes in a disc of radius r on a sphere of area 4π
    scenes["sphere surface"] = (probes, pts, nrm.astype(np.float32),
                                float(np.sqrt(args.neighbours * 4 / P)))
    probes = rng.uniform(0, 1, (P, 3)).astype(np.float32)
    pts = rng.uniform(0, 1, (N, 3)).astype(np.float32)
    nrm = rng.normal(size=(N, 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    scenes["uniform cube"] = (probes, pts, nrm,
                              float((args.neighbours * 3 / (4 * np.pi * P)) ** (1 / 3)))

    print(f"N={N} points, P={P} probes, k={k}, threads={dr.thread_count()}")
    hdr = (f"{'scene':<16}{'radius':>8}{'mean#':>7}{'fallbk':>8}{'build':>9}{'1st call':>10}"
           f"{'drjit':>9}{'cKDTree':>10}{'cKD x2':>9}{'cKDTree+w':>11}{'ratio':>8}")
    print(hdr)
    print("-" * len(hdr))
    for name, (probes, pts, nrm, radius) in scenes.items():
        t = time.perf_counter()
        grid = ProbeGrid(probes, radius)
        t_build = time.perf_counter() - t
        x = to_jit(mi.Point3f, pts.T)
        n = to_jit(mi.Vector3f, nrm.T)
        dr.eval(x, n)

        def ours():
            r = query(grid, x, n, k)
            dr.eval(r.index, r.weight, r.count)
            return r

        t = time.perf_counter()
        res = ours()
        t_first = time.perf_counter() - t
        t_ours = timed(ours, args.repeat)

        tree = cKDTree(probes.astype(np.float64))
        p64, n64 = pts.astype(np.float64), nrm.astype(np.float64)
        pr64 = probes.astype(np.float64)

        def kd(workers=1):
            return tree.query(p64, k=k, distance_upper_bound=radius, workers=workers)

        def kd_w():
            dist, idx = kd()
            return numpy_weights(pr64, p64, n64, idx, dist, radius)

        t_kd = timed(kd, args.repeat)
        t_kd2 = timed(lambda: kd(-1), args.repeat)
        t_kdw = timed(kd_w, args.repeat)
        mean = float(np.asarray(res.count).mean())
        print(f"{name:<16}{radius:>8.4f}{mean:>7.1f}{res.n_fallback:>8d}{t_build*1e3:>7.1f}ms"
              f"{t_first*1e3:>8.1f}ms{t_ours*1e3:>7.1f}ms{t_kd*1e3:>8.1f}ms{t_kd2*1e3:>7.1f}ms"
              f"{t_kdw*1e3:>9.1f}ms{t_kdw/t_ours:>7.2f}x")
    print("ratio = (cKDTree + numpy weights, 1 worker) / drjit query (indices + weights)")


if __name__ == "__main__":
    main()
