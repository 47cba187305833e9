"""G-buffer benchmark: ours (``surfel_gbuffer`` raster / trace) vs Mitsuba's ``volprim_rf_basic``.

One run prints one table, side by side, on one 3DGS PLY: per resolution, forward and
forward+backward times of

* ours (raster) — ``surfel_gbuffer`` with ``method='raster'`` (tile rasteriser),
* ours (trace)  — ``surfel_gbuffer`` with ``method='trace'`` (K BVH traversals per ray),
* volprim       — Mitsuba 3's ``volprim_rf_basic`` on the same file as 3D Gaussians,
  loaded by Mitsuba's own 3DGS PLY reader, once as analytic ``ellipsoids`` and once as
  ``ellipsoidsmesh`` (triangle shells; Mitsuba's choice for hardware ray tracing — on
  the LLVM/Embree backend the analytic shape measured faster); the "volprim/x" ratios
  use the faster of the two,

with peak resident memory, then the scaling of ours with the surfel count
(synthetic surfels) and the ratios the targets are stated in. Every (method,
resolution) runs in a fresh subprocess, one after the other, so peak memory and JIT
caches do not leak between rows; all ratios come from the same invocation.

    python benchmarks/gbuffer.py                         # generated 50k-splat 3DGS file, 256² and 512²
    python benchmarks/gbuffer.py --ply point_cloud.ply   # any 3DGS / 2DGS PLY
    python benchmarks/gbuffer.py --quick                 # smoke run, 3k splats at 48² (~15 s)
    python benchmarks/gbuffer.py --scaling 10000 100000 1000000 --scaling-res 512

Without ``--ply`` a 3DGS-layout PLY (x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity
scale_0..2 rot_0..3) is generated into a temporary directory: splats on a sphere and a
ground slab, anisotropic and thin in the normal direction (the thin axis at a random
position of the three, unnormalised quaternions), mixed opacities, SH degree 3, and a
few percent of low-opacity 3D floaters. Camera: ``--camera``, else a 3DGS
``cameras.json`` next to the file (up to three directories up; ``--camera-index``),
else an oblique view of the splats' bulk (z up).

What is timed: ``mi.render(scene, spp=1)`` (box filter) followed by ``dr.eval`` and
``dr.sync_thread``; 'first' is the first call in the fresh process (tracing, JIT
compilation or loading from Dr.Jit's on-disk kernel cache, and the work); the other
columns are the median of ``--repeats`` later calls. Forward+backward is
``mi.render(scene, params)`` + ``dr.backward(dr.sum(image))`` to every splat parameter
(ours: means, quats, log_scales, opacity_logit, sh; volprim: its differentiable
``data`` (centres/scales/quaternions), ``sh_coeffs``, ``opacities``). Memory: peak RSS
(``ru_maxrss``) of each phase (load, forward, forward+backward; reset between phases by
``/proc/self/clear_refs`` where Linux allows it, else the process peak so far).

Raster rows also report the host-side part of the raster path (``surfel_geometry`` +
``bin_surfels``, run on every render): its time, its tile entries, the tile-list
length a ray walks at most, and its peak NumPy allocation (tracemalloc). Volprim rays
are Mitsuba's (random sub-pixel positions), ``srgb_primitives`` is off so both
renderers output the SH colour as is. The last lines give the ratios of the targets
(time of the other / time of ours).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814
RESULT_TAG = "@@gbuffer-result "
OURS_KEYS = ("means", "quats", "log_scales", "opacity_logit", "sh")
SHAPE_ID = "splats"
LABELS = {"raster": "ours (raster)", "trace": "ours (trace)", "volprim": "volprim_rf_basic"}


# =========================================================================== synthetic splats
def synth_gaussians(n: int, seed: int = 0, sh_degree: int = 3, floaters: float = 0.04) -> dict:
    """Raw 3DGS parameters of ``n`` splats on a sphere (r = 0.8) and a ground slab.

    Returns {means [N,3], quats [N,4] (w-first, unnormalised), log_scales [N,3],
    opacity [N] (logit), f_dc [N,3], f_rest [N, 3(K-1)] (channel-major)} as float32.
    Surface splats are flat (thin axis 0.02–0.3 of the smaller tangent scale), placed at a
    random one of the three axes as trained 3DGS files have them; tangent scales spread
    log-normally around σ = TILING · sqrt(A / (N π)) (the ``from_mesh`` spacing); normals
    tilted by ~6° and centres spread by 0.1 σ along them (no exactly coplanar splats).
    """
    import trimesh

    from comgs_dr.surfels.from_mesh import TILING, frame_to_quat

    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    ground = trimesh.creation.box((2.5, 2.5, 0.1),
                                  transform=trimesh.transformations.translation_matrix([0, 0, -0.9]))
    mesh = trimesh.util.concatenate([sphere, ground])
    n_float = int(round(n * floaters)) if n >= 100 else 0
    n_surf = n - n_float
    pos, face = trimesh.sample.sample_surface(mesh, n_surf, seed=seed)
    nrm = np.asarray(mesh.face_normals, np.float64)[face]
    sigma = TILING * math.sqrt(float(mesh.area) / (n_surf * math.pi))
    # trained splats are not exactly coplanar: tilt normals (~6°), spread along them
    nrm = nrm + rng.normal(0.0, 0.1, nrm.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pos = pos + nrm * rng.normal(0.0, 0.1 * sigma, (n_surf, 1))
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    a = np.cross(nrm, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(nrm, a)
    th = rng.uniform(0, 2 * np.pi, (n_surf, 1))                    # random in-plane orientation
    t_u = np.cos(th) * a + np.sin(th) * b
    t_v = np.cross(nrm, t_u)
    s_uv = sigma * np.exp(rng.normal(0.0, 0.35, (n_surf, 2)))
    s_n = s_uv.min(1) * np.exp(rng.uniform(np.log(0.02), np.log(0.3), n_surf))
    # thin axis at position k: columns (a_k, a_k+1, a_k+2) = (n, t_u, t_v), a proper rotation
    k = rng.integers(0, 3, n_surf)
    cols = [np.empty((n_surf, 3)) for _ in range(3)]
    scales = np.empty((n_surf, 3))
    rows = np.arange(n_surf)
    for j, (vec, s) in enumerate(((nrm, s_n), (t_u, s_uv[:, 0]), (t_v, s_uv[:, 1]))):
        pos_j = (k + j) % 3
        for c in range(3):
            m = pos_j == c
            cols[c][m] = vec[m]
        scales[rows, pos_j] = s
    q_surf = frame_to_quat(np.stack(cols, 2))
    # colours: smooth bands on the sphere, a checker on the ground
    on_sphere = pos[:, 2] > -0.84
    col = np.where(on_sphere[:, None],
                   0.5 + 0.35 * np.sin(np.c_[3 * pos[:, 0], 3 * pos[:, 1] + 1, 4 * pos[:, 2] + 2]),
                   np.where(((np.floor(pos[:, 0] * 4) + np.floor(pos[:, 1] * 4)) % 2 == 0)[:, None],
                            [[0.8, 0.8, 0.75]], [[0.25, 0.3, 0.35]]))
    op_surf = np.where(rng.random(n_surf) < 0.75, rng.normal(3.0, 1.0, n_surf),
                       rng.uniform(-3.0, 1.0, n_surf))
    # floaters: low-opacity, round-ish 3D Gaussians in the volume
    f_pos = rng.uniform([-1.2, -1.2, -0.8], [1.2, 1.2, 1.2], (n_float, 3))
    f_q = rng.normal(size=(n_float, 4))
    f_q /= np.linalg.norm(f_q, axis=1, keepdims=True)
    f_s = sigma * np.exp(rng.normal(1.0, 0.5, (n_float, 1))) * rng.uniform(0.3, 1.0, (n_float, 3))
    f_col = rng.uniform(0.2, 0.8, (n_float, 3))
    f_op = rng.normal(-2.5, 1.0, n_float)

    quats = np.concatenate([q_surf, f_q])
    quats *= (rng.choice([-1.0, 1.0], len(quats)) * rng.uniform(0.5, 2.0, len(quats)))[:, None]
    K = (sh_degree + 1) ** 2
    band = np.repeat(np.arange(sh_degree + 1), 2 * np.arange(sh_degree + 1) + 1)[1:]  # [K-1]
    f_rest = rng.normal(0.0, 1.0, (n, 3, K - 1)) * (0.12 / band)  # weaker in higher bands
    return {"means": np.concatenate([pos, f_pos]).astype(np.float32),
            "quats": quats.astype(np.float32),
            "log_scales": np.log(np.concatenate([scales, f_s])).astype(np.float32),
            "opacity": np.concatenate([op_surf, f_op]).astype(np.float32),
            "f_dc": ((np.concatenate([col, f_col]) - 0.5) / SH_C0).astype(np.float32),
            "f_rest": f_rest.reshape(n, 3 * (K - 1)).astype(np.float32)}


def write_3dgs_ply(path, g: dict) -> None:
    """Write raw 3DGS parameters (:func:`synth_gaussians` layout) in the 3DGS PLY layout."""
    import plyfile

    n = len(g["means"])
    cols = ([(c, g["means"][:, i]) for i, c in enumerate("xyz")]
            + [(c, np.zeros(n, np.float32)) for c in ("nx", "ny", "nz")]
            + [(f"f_dc_{i}", g["f_dc"][:, i]) for i in range(3)]
            + [(f"f_rest_{i}", g["f_rest"][:, i]) for i in range(g["f_rest"].shape[1])]
            + [("opacity", g["opacity"])]
            + [(f"scale_{i}", g["log_scales"][:, i]) for i in range(3)]
            + [(f"rot_{i}", g["quats"][:, i]) for i in range(4)])
    arr = np.empty(n, dtype=[(c, "<f4") for c, _ in cols])
    for c, v in cols:
        arr[c] = v
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], text=False,
                    byte_order="<").write(os.fspath(path))


def synth_surfels(n: int, seed: int = 0):
    """:func:`synth_gaussians` flattened to surfels as ``load_ply`` flattens a 3DGS file."""
    from comgs_dr.surfels import SurfelParams
    from comgs_dr.surfels.io import flatten_gaussians

    g = synth_gaussians(n, seed)
    K = g["f_rest"].shape[1] // 3 + 1
    sh = np.empty((n, K, 3), np.float32)
    sh[:, 0] = g["f_dc"]
    sh[:, 1:] = g["f_rest"].reshape(n, 3, K - 1).transpose(0, 2, 1)
    q, ls = flatten_gaussians(g.pop("quats"), g.pop("log_scales"))
    return SurfelParams.from_numpy(means=g["means"], quats=q, log_scales=ls,
                                   opacity_logit=g["opacity"], sh=sh)


# =========================================================================== PLY → volprim
def ply_summary(path) -> dict:
    """Splat count, scale count and SH degree of a PLY (header only)."""
    import plyfile

    with open(path, "rb") as f:
        el = plyfile.PlyData.read(f, mmap=True)["vertex"]
        names = [p.name for p in el.properties]
        count = int(el.count)
    n_rest = sum(1 for c in names if c.startswith("f_rest_"))
    return {"count": count, "n_scales": 3 if "scale_2" in names else 2,
            "sh_degree": {0: 0, 9: 1, 24: 2, 45: 3}.get(n_rest, -1), "properties": names}


def volprim_tensors(path) -> dict:
    """A 3DGS (or 2DGS) PLY as the tensors of Mitsuba's ``ellipsoids``/``ellipsoidsmesh``.

    The conversion Mitsuba's 3DGS PLY reader (``src/shapes/ellipsoids.h``) applies:
    centres as is; scales exp(scale_i) ≥ 1e-6; quaternions reordered w-first → (x, y, z, w)
    and normalised; ``opacities`` [N, 1] = sigmoid(opacity) clipped to [1e-8, 1 − 1e-8];
    ``sh_coeffs`` [N, 3K] coefficient-major (coefficient j of channel c at 3j + c), from
    f_dc and the channel-major f_rest. A 2DGS file (2 scales) gets a third scale of 1e-3 ×
    the smaller one (a flat ellipsoid). Used when Mitsuba's reader refuses the file
    (property order other than 3DGS's).
    """
    import mitsuba as mi
    import plyfile

    from comgs_dr.core.hostarray import to_jit

    with open(path, "rb") as f:
        el = plyfile.PlyData.read(f)["vertex"]
    names = {p.name for p in el.properties}

    def col(c):
        return np.asarray(el[c], np.float64)

    n = int(el.count)
    centers = np.stack([col(c) for c in "xyz"], 1)
    if "scale_2" in names:
        scales = np.exp(np.stack([col(f"scale_{i}") for i in range(3)], 1))
    else:
        s2 = np.exp(np.stack([col("scale_0"), col("scale_1")], 1))
        scales = np.c_[s2, 1e-3 * s2.min(1)]
    scales = np.maximum(scales, 1e-6)
    q = np.stack([col("rot_1"), col("rot_2"), col("rot_3"), col("rot_0")], 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    op = np.clip(1.0 / (1.0 + np.exp(-col("opacity"))), 1e-8, 1 - 1e-8)[:, None]
    n_rest = sum(1 for c in names if c.startswith("f_rest_"))
    K = n_rest // 3 + 1
    sh = np.empty((n, K, 3))
    sh[:, 0] = np.stack([col(f"f_dc_{i}") for i in range(3)], 1)
    if K > 1:
        rest = np.stack([col(f"f_rest_{i}") for i in range(n_rest)], 1)
        sh[:, 1:] = rest.reshape(n, 3, K - 1).transpose(0, 2, 1)

    def T(a):
        return to_jit(mi.TensorXf, a)

    return {"centers": T(centers), "scales": T(scales), "quaternions": T(q),
            "opacities": T(op), "sh_coeffs": T(sh.reshape(n, 3 * K))}


# =========================================================================== camera
def camera_spec(args, ply: Path | None, generated: bool) -> dict:
    """{'origin', 'target', 'up', 'fov'} or {'to_world', 'fov'}, plus 'source'."""
    if args.camera:
        v = list(map(float, args.camera))
        if len(v) not in (6, 9):
            raise SystemExit("--camera takes ox oy oz tx ty tz [ux uy uz]")
        return {"origin": v[:3], "target": v[3:6], "up": v[6:9] if len(v) == 9 else [0, 0, 1],
                "fov": args.fov, "source": "--camera"}
    if generated:
        return {"origin": [0.0, -3.2, 1.6], "target": [0.0, 0.0, -0.1], "up": [0, 0, 1],
                "fov": args.fov, "source": "generated scene"}
    for d in list(ply.resolve().parents)[:3]:
        cj = d / "cameras.json"
        if cj.is_file():
            cams = json.loads(cj.read_text())
            c = cams[args.camera_index % len(cams)]
            m = np.eye(4)
            m[:3, :3] = np.asarray(c["rotation"], np.float64)          # camera → world (OpenCV axes)
            m[:3, 3] = np.asarray(c["position"], np.float64)
            m = m @ np.diag([-1.0, -1.0, 1.0, 1.0])                     # OpenCV → Mitsuba (x left, y up)
            fov = math.degrees(2 * math.atan(c["width"] / (2 * c["fx"])))
            return {"to_world": m.tolist(), "fov": fov,
                    "source": f"{cj} #{args.camera_index % len(cams)} ({c.get('img_name', '?')})"}
    import plyfile
    with open(ply, "rb") as f:
        el = plyfile.PlyData.read(f, mmap=True)["vertex"]
        xyz = np.stack([np.asarray(el[c], np.float64) for c in "xyz"], 1)
    centre = np.median(xyz, 0)
    r = float(np.percentile(np.linalg.norm(xyz - centre, axis=1), 90))
    d = np.array([0.0, -1.0, 0.5]) / math.sqrt(1.25)
    return {"origin": (centre + 2.2 * r * d).tolist(), "target": centre.tolist(), "up": [0, 0, 1],
            "fov": args.fov, "source": "auto (oblique view of the splats' 90% radius, z up)"}


def sensor_dict(cam: dict, res: int) -> dict:
    from comgs_dr.core import cameras
    if "to_world" in cam:
        return cameras.from_matrix(cam["to_world"], cam["fov"], res)
    return cameras.perspective(cam["origin"], cam["target"], cam["up"], fov=cam["fov"], res=res)


# =========================================================================== one measurement
def _reset_peak() -> bool:
    """Reset the kernel's RSS high-water mark (Linux ≥ 4.0); False where not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / (1024 if sys.platform != "darwin"
                                                                    else 1024 ** 2)


def run_one(cfg: dict) -> dict:
    """Load, time and measure one (method, resolution, scene) in this process."""
    res = {"method": cfg["method"], "res": cfg["res"]}
    can_reset = _reset_peak()
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    import drjit as dr
    import mitsuba as mi

    res["base_mb"] = _peak_mb()
    t0 = time.perf_counter()
    sensor = sensor_dict(cfg["camera"], cfg["res"])
    method = cfg["method"]
    if method == "volprim":
        vp = {"type": "volprim_rf_basic", "max_depth": cfg["volprim_depth"], "srgb_primitives": False}
        shape = {"type": cfg["volprim_shape"]}
        scene, why = None, None
        if cfg["volprim_load"] == "file":
            try:
                scene = mi.load_dict({"type": "scene", "integrator": vp, "sensor": sensor,
                                      SHAPE_ID: {**shape, "filename": cfg["ply"]}})
                res["volprim_load"] = "Mitsuba's PLY reader"
            except Exception as e:                    # not the 3DGS property order
                why = str(e).strip().splitlines()[-1][:160]
        if scene is None:
            scene = mi.load_dict({"type": "scene", "integrator": vp, "sensor": sensor,
                                  SHAPE_ID: {**shape, **volprim_tensors(cfg["ply"])}})
            res["volprim_load"] = "tensors" + (f" (reader refused: {why})" if why else "")
        mp = mi.traverse(scene)
        keys = [f"{SHAPE_ID}.{k}" for k in ("data", "sh_coeffs", "opacities") if f"{SHAPE_ID}.{k}" in mp]
        res["n"] = dr.width(mp[f"{SHAPE_ID}.data"]) // 10
    else:
        from comgs_dr.surfels.io import load_ply
        from comgs_dr.surfels.scene import gbuffer_scene
        params = synth_surfels(cfg["synthetic"], seed=0) if cfg.get("synthetic") else load_ply(cfg["ply"])
        res["n"] = params.count
        scene = gbuffer_scene({SHAPE_ID: params}, sensor, max_hits=cfg["K"],
                              targets=cfg["targets"], method=method)
        del params
        mp = mi.traverse(scene)
        keys = [f"{SHAPE_ID}.{k}" for k in OURS_KEYS]
    dr.eval()
    dr.sync_thread()
    res["load_s"] = time.perf_counter() - t0
    res["load_mb"] = _peak_mb()
    res["keys"] = keys

    def timed(fn):
        t = time.perf_counter()
        fn()
        return time.perf_counter() - t

    def fwd():
        dr.eval(mi.render(scene, spp=1))
        dr.sync_thread()

    def fwd_bwd(stats=None):
        for k in keys:
            dr.enable_grad(mp[k])
        img = mi.render(scene, mp, spp=1)
        dr.backward(dr.sum(img, axis=None))
        dr.eval([dr.grad(mp[k]) for k in keys])
        dr.sync_thread()
        if stats is not None:         # first call only: finite / non-zero gradients (Dr.Jit reductions)
            for k in keys:
                g = dr.grad(mp[k])
                stats[k] = (bool(dr.all(dr.isfinite(g), axis=None)),
                            float(dr.count(g != 0, axis=None)[0]) / max(math.prod(dr.shape(g)), 1))
        for k in keys:
            dr.disable_grad(mp[k])

    def median(xs):
        return float(np.median(xs)) if xs else float("nan")

    rep = cfg["repeats"]
    if can_reset:
        _reset_peak()
    res["first_fwd"] = timed(fwd)
    res["fwd"] = median([timed(fwd) for _ in range(rep)])
    res["fwd_mb"] = _peak_mb()
    if not cfg.get("no_backward"):
        if can_reset:
            _reset_peak()
        stats = {}
        res["first_fwd_bwd"] = timed(lambda: fwd_bwd(stats))
        res["fwd_bwd"] = median([timed(fwd_bwd) for _ in range(rep)])
        res["fwd_bwd_mb"] = _peak_mb()
        res["grad_finite"] = all(f for f, _ in stats.values())
        res["grad_nonzero"] = {k.split(".", 1)[1]: nz for k, (_, nz) in stats.items()}
    res["peak_reset_per_phase"] = can_reset

    img = mi.render(scene, spp=1)
    if method == "volprim":
        out = {"color": np.array(img)[..., :3]}
    else:
        out = {k: np.array(v) for k, v in scene.integrator().split(img).items()
               if k in ("color", "weight")}
        if "weight" in out:
            res["coverage"] = float((out["weight"] > 0.5).mean())
    if cfg.get("save"):
        np.savez(cfg["save"], **out)
    if method == "raster":
        res.update(raster_breakdown(scene, rep))
    return res


def raster_breakdown(scene, repeats: int) -> dict:
    """Time and NumPy peak of the raster path's projection + binning (run on every render)."""
    import tracemalloc

    from comgs_dr.surfels import composite, raster
    shapes = composite.surfel_shapes(scene, "surfel_gbuffer")
    sensor = scene.sensors()[0]
    ts = {"geom": [], "bin": []}
    for _ in range(max(repeats, 1)):
        t = time.perf_counter()
        view = raster.pinhole_view(sensor)
        geo = raster.surfel_geometry(shapes)
        ts["geom"].append(time.perf_counter() - t)
        t = time.perf_counter()
        lists = raster.bin_surfels(geo, view)
        ts["bin"].append(time.perf_counter() - t)
        del lists
    tracemalloc.start()
    geo = raster.surfel_geometry(shapes)
    geom_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    lists = raster.bin_surfels(geo, raster.pinhole_view(sensor))
    bin_peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    # tile-list length each ray walks at most (its tile's entries), averaged over the rays
    W, H = raster.pinhole_view(sensor).crop_size
    ntx, nty = -(-W // raster.TILE), -(-H // raster.TILE)
    px = np.minimum(raster.TILE, W - raster.TILE * np.arange(ntx))
    py = np.minimum(raster.TILE, H - raster.TILE * np.arange(nty))
    per_tile = (np.array(lists.end, np.float64) - np.array(lists.start, np.float64))
    list_per_ray = float((per_tile * np.outer(py, px).ravel()).sum() / (W * H))
    return {"geom_s": float(np.median(ts["geom"])), "bin_s": float(np.median(ts["bin"])),
            "entries": int(lists.entries), "list_per_ray": list_per_ray,
            "geom_np_mb": geom_peak / 2 ** 20, "bin_np_mb": bin_peak / 2 ** 20}


# =========================================================================== driver
def _spawn(cfg: dict, timeout: float) -> dict:
    try:
        out = subprocess.run([sys.executable, os.path.abspath(__file__), "--_one", json.dumps(cfg)],
                             capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    for line in reversed(out.stdout.splitlines()):
        if line.startswith(RESULT_TAG):
            return json.loads(line[len(RESULT_TAG):])
    if out.returncode < 0:
        sig = -out.returncode
        why = "killed by SIGKILL (out of memory?)" if sig == 9 else f"killed by signal {sig}"
        return {"error": why}
    err = [ln for ln in out.stderr.strip().splitlines() if ln.strip()]
    return {"error": (err[-1] if err else f"exit code {out.returncode}")[:200]}


def _f(x, w, p):
    return f"{x:>{w}.{p}f}" if isinstance(x, (int, float)) and x == x else f"{'-':>{w}}"


def _ratio(a, b):
    """a / b when both are measured, else None."""
    if a is None or b is None or not (a > 0 and b > 0):
        return None
    return a / b


def _mad(a: dict, b: dict, key="color"):
    if a is None or b is None or key not in a or key not in b:
        return None
    return float(np.abs(a[key] - b[key]).mean())


def header(args, scene_desc: str, cam: dict) -> list[str]:
    import drjit
    import mitsuba
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return [
        f"# machine: {cpu}, {os.cpu_count()} cores ({usable} usable), {platform.system()}, "
        f"load avg {load:.1f} at start | python {platform.python_version()}, mitsuba "
        f"{mitsuba.__version__}, drjit {drjit.__version__}, numpy {np.__version__}, llvm_ad_rgb | "
        f"code: {_code_version()}",
        f"# scene: {scene_desc}; camera: {cam['source']}",
        f"# ours: surfel_gbuffer K={args.K}, targets={args.targets}, rays through pixel centres | "
        f"volprim: volprim_rf_basic (max_depth {args.volprim_depth}, srgb_primitives false) on "
        f"{' / '.join(args.volprim_shapes)}, random sub-pixel rays",
        f"# timed: mi.render spp=1 box filter + dr.eval + sync; 'first' = first call in a fresh "
        f"process (JIT or kernel cache + work), fwd / f+b = median of {args.repeats}; "
        "f+b = render + dr.backward(sum(image)) to all splat parameters",
        "# memory: peak RSS (ru_maxrss) per phase: load, fwd, f+b (reset between phases) | "
        "raster only: np = NumPy projection+binning per render (s, tracemalloc peak MB), "
        "list = tile-list entries per ray",
    ]


def _code_version() -> str:
    """git commit of the checkout, and which renderer files differ from it."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                              text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "comgs_dr/surfels",
                                "comgs_dr/integrators"], cwd=root, capture_output=True, text=True,
                               timeout=10).stdout.split("\n")
    except (OSError, subprocess.SubprocessError):
        return "unknown (no git)"
    import hashlib

    def tag(rel):
        f = root / rel
        h = hashlib.sha1(f.read_bytes()).hexdigest()[:8] if f.is_file() else "deleted"
        return f"{f.name} ({h})"
    changed = [tag(ln[3:].strip()) for ln in dirty if ln.strip()]
    return (head or "unknown") + (f" + local changes to {', '.join(changed)}" if changed else "")


def _methods(args) -> list[tuple[str, dict]]:
    """(row key, config overrides) of the main table, volprim once per shape type."""
    out = []
    for m in args.methods:
        if m == "volprim":
            out += [(f"volprim:{sh}", {"method": "volprim", "volprim_shape": sh})
                    for sh in args.volprim_shapes]
        else:
            out.append((m, {"method": m}))
    return out


def _label(key: str) -> str:
    if key.startswith("volprim:"):
        return {"ellipsoidsmesh": "volprim (mesh)", "ellipsoids": "volprim (ellips.)"}.get(
            key[8:], "volprim " + key[8:])
    return LABELS[key]


def _best(rows: dict, prefix: str, field: str):
    """(value, key) of the fastest measured row whose key starts with ``prefix``."""
    c = [(r[field], k) for k, r in rows.items() if k.startswith(prefix) and r.get(field)]
    return min(c) if c else (None, None)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ply", help="3DGS/2DGS PLY (default: generate a 3DGS-layout file)")
    ap.add_argument("--splats", type=int, default=50_000, help="splats of the generated file")
    ap.add_argument("--res", type=int, nargs="*", default=[256, 512],
                    help="resolutions of the main table (none: skip it)")
    ap.add_argument("--K", type=int, default=32, help="max hits per ray of ours")
    ap.add_argument("--targets", default="all", help="surfel_gbuffer targets (default: all)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--methods", nargs="+", default=["raster", "trace", "volprim"],
                    choices=["raster", "trace", "volprim"])
    ap.add_argument("--scaling", type=int, nargs="*", default=[10_000, 100_000, 1_000_000],
                    help="surfel counts of the scaling table (none: skip it)")
    ap.add_argument("--scaling-res", type=int, default=512)
    ap.add_argument("--trace-max", type=int, default=100_000,
                    help="largest surfel count the trace path is run at in the scaling table")
    ap.add_argument("--volprim-shapes", nargs="+", default=["ellipsoids", "ellipsoidsmesh"],
                    choices=["ellipsoidsmesh", "ellipsoids"],
                    help="Mitsuba shape types for volprim, one row each; ratios use the fastest")
    ap.add_argument("--volprim-depth", type=int, default=64, help="volprim_rf_basic max_depth")
    ap.add_argument("--volprim-load", default="file", choices=["file", "tensors"],
                    help="file: Mitsuba's own 3DGS PLY reader (tensors if it refuses the file); "
                         "tensors: converted here (volprim_tensors)")
    ap.add_argument("--camera", nargs="+", metavar="X", help="ox oy oz tx ty tz [ux uy uz]")
    ap.add_argument("--camera-index", type=int, default=0, help="entry of a 3DGS cameras.json")
    ap.add_argument("--fov", type=float, default=45.0, help="horizontal fov (unless cameras.json)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per row")
    ap.add_argument("--json", help="also write all results to this JSON file")
    ap.add_argument("--quick", action="store_true",
                    help="smoke-run defaults: 3000 generated splats, 48², 1 repeat, volprim on "
                         "ellipsoids only, scaling: raster at 3000 (explicit options win)")
    ap.add_argument("--_one", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a._one:
        print(RESULT_TAG + json.dumps(run_one(json.loads(a._one))), flush=True)
        return
    if a.quick:                    # smaller defaults; options given explicitly still win
        quick = {"splats": 3000, "res": [48], "repeats": 1, "volprim_shapes": ["ellipsoids"],
                 "scaling": [3000], "scaling_res": 48, "trace_max": 0}
        for k, v in quick.items():
            if getattr(a, k) == ap.get_default(k):
                setattr(a, k, v)

    with tempfile.TemporaryDirectory(prefix="gbuffer-bench-") as tmp:
        tmp = Path(tmp)
        if a.ply:
            ply, generated = Path(a.ply), False
            if not ply.is_file():
                raise SystemExit(f"--ply: {ply} not found")
        else:
            ply, generated = tmp / f"synthetic_3dgs_{a.splats}.ply", True
            if a.res:
                write_3dgs_ply(ply, synth_gaussians(a.splats, seed=0))
        cam = camera_spec(a, ply, generated)
        cam_json = {k: v for k, v in cam.items() if k != "source"}
        if a.res:
            info = ply_summary(ply)
            desc = (f"{'generated ' if generated else ''}{ply.name}: {info['count']} splats, "
                    f"{info['n_scales']} scales"
                    f"{' (flattened to surfels for ours)' if info['n_scales'] == 3 else ''}, "
                    f"SH degree {info['sh_degree']}")
        else:
            desc = "none (main table skipped: --res without values)"
        lines = header(a, desc, cam)
        for ln in lines:
            print(ln, flush=True)
        results = {"header": lines, "main": [], "checks": {}, "scaling": [], "summary": []}
        per_res = {}
        if a.res:
            hdr = (f"{'res':>4} {'method':<17} {'splats':>8} {'first fwd':>9} {'fwd s':>7} "
                   f"{'first f+b':>9} {'f+b s':>7} {'f+b/fwd':>7} {'load MB':>7} {'fwd MB':>7} "
                   f"{'f+b MB':>7} {'np s':>6} {'np MB':>6} {'list':>6} {'cover':>5} "
                   f"{'volprim/x fwd':>13} {'volprim/x f+b':>13}")
            print(hdr)
            print("-" * len(hdr), flush=True)
        for res in a.res:
            rows, imgs = {}, {}
            for key, over in _methods(a):
                save = tmp / f"img_{key.replace(':', '_')}_{res}.npz"
                cfg = {"res": res, "K": a.K, "targets": a.targets, "repeats": a.repeats,
                       "ply": str(ply), "camera": cam_json, "save": str(save),
                       "volprim_depth": a.volprim_depth, "volprim_load": a.volprim_load, **over}
                r = _spawn(cfg, a.timeout)
                r.update(key=key, method=over["method"], res=res)
                if "volprim_shape" in over:
                    r["volprim_shape"] = over["volprim_shape"]
                rows[key] = r
                imgs[key] = dict(np.load(save)) if save.exists() else None
                results["main"].append(r)
            vf, _ = _best(rows, "volprim", "fwd")
            vb, _ = _best(rows, "volprim", "fwd_bwd")
            for key, r in rows.items():
                if "error" in r:
                    why = r["error"]
                    if r["method"] == "volprim":
                        why = f"volprim_rf_basic unavailable or failed: {why}"
                    print(f"{res:>4} {_label(key):<17} FAILED: {why}", flush=True)
                    continue
                np_s = r["geom_s"] + r["bin_s"] if "bin_s" in r else None
                print(f"{res:>4} {_label(key):<17} {r['n']:>8} {_f(r['first_fwd'], 9, 2)} "
                      f"{_f(r['fwd'], 7, 3)} {_f(r.get('first_fwd_bwd'), 9, 2)} "
                      f"{_f(r.get('fwd_bwd'), 7, 3)} {_f(_ratio(r.get('fwd_bwd'), r.get('fwd')), 7, 2)} "
                      f"{_f(r['load_mb'], 7, 0)} {_f(r['fwd_mb'], 7, 0)} {_f(r.get('fwd_bwd_mb'), 7, 0)} "
                      f"{_f(np_s, 6, 3)} {_f(r.get('bin_np_mb'), 6, 0)} {_f(r.get('list_per_ray'), 6, 0)} "
                      f"{_f(r.get('coverage'), 5, 3)} {_f(_ratio(vf, r.get('fwd')), 12, 2)}× "
                      f"{_f(_ratio(vb, r.get('fwd_bwd')), 12, 2)}×", flush=True)
            checks = []
            d = _mad(imgs.get("raster"), imgs.get("trace"))
            if d is not None:
                dw = _mad(imgs["raster"], imgs["trace"], "weight")
                frac = float((np.abs(imgs["raster"]["color"] - imgs["trace"]["color"]).max(-1) > 1e-3).mean())
                checks.append(f"mean |raster − trace|: colour {d:.2e}"
                              + ("" if dw is None else f", weight {dw:.2e}")
                              + f"; pixels differing > 1e-3: {100 * frac:.2f}%")
            for key in rows:
                d = _mad(imgs.get("raster"), imgs.get(key)) if key.startswith("volprim") else None
                if d is not None:
                    checks.append(f"mean |raster − {_label(key)}| colour {d:.3f} (3D Gaussians vs "
                                  "flattened surfels, jittered vs centred rays: not expected to match)")
            for key, r in rows.items():
                if r.get("grad_finite") is False:
                    checks.append(f"{_label(key)}: NON-FINITE gradients")
                if "volprim_load" in r:
                    checks.append(f"{_label(key)} loaded by {r['volprim_load']}")
            for c in checks:
                print(f"     · {c}", flush=True)
            results["checks"][str(res)] = checks
            per_res[res] = rows

        if a.scaling:
            print(flush=True)
            print(f"# scaling of ours: synthetic surfels (the generator above, flattened), "
                  f"{a.scaling_res}² rays, K={a.K}, trace up to {a.trace_max} surfels", flush=True)
            sh = (f"{'surfels':>8} {'method':<14} {'first fwd':>9} {'fwd s':>7} {'f+b s':>7} "
                  f"{'np s':>6} {'np MB':>6} {'entries':>9} {'list':>6} {'load MB':>7} {'fwd MB':>7} "
                  f"{'f+b MB':>7}")
            print(sh)
            print("-" * len(sh), flush=True)
            for n in a.scaling:
                for m in ("raster", "trace"):
                    if m not in a.methods or (m == "trace" and n > a.trace_max):
                        continue
                    cfg = {"method": m, "res": a.scaling_res, "K": a.K, "targets": a.targets,
                           "repeats": a.repeats, "synthetic": n,
                           "camera": {"origin": [0.0, -3.2, 1.6], "target": [0.0, 0.0, -0.1],
                                      "up": [0, 0, 1], "fov": 45.0}}
                    r = _spawn(cfg, a.timeout)
                    r.update(method=m, n_requested=n, res=a.scaling_res)
                    results["scaling"].append(r)
                    if "error" in r:
                        print(f"{n:>8} {LABELS[m]:<14} FAILED: {r['error']}", flush=True)
                        continue
                    np_s = r["geom_s"] + r["bin_s"] if "bin_s" in r else None
                    print(f"{n:>8} {LABELS[m]:<14} {_f(r['first_fwd'], 9, 2)} {_f(r['fwd'], 7, 3)} "
                          f"{_f(r.get('fwd_bwd'), 7, 3)} {_f(np_s, 6, 3)} {_f(r.get('bin_np_mb'), 6, 0)} "
                          f"{r.get('entries', '-'):>9} {_f(r.get('list_per_ray'), 6, 0)} "
                          f"{_f(r['load_mb'], 7, 0)} {_f(r['fwd_mb'], 7, 0)} "
                          f"{_f(r.get('fwd_bwd_mb'), 7, 0)}", flush=True)

        summary = []
        for res, rows in per_res.items():
            vf, vk = _best(rows, "volprim", "fwd")
            r, t = rows.get("raster", {}), rows.get("trace", {})
            rf = _ratio(vf, r.get("fwd"))
            tf = _ratio(vf, t.get("fwd"))
            rb = _ratio(t.get("fwd_bwd"), r.get("fwd_bwd"))
            vs = f" ({_label(vk)})" if vk else ""
            vf_txt = ("-" if rf is None else "meets target ≥ 5×" if rf >= 5 else
                      "meets floor ≥ 2×, target 5×" if rf >= 2 else "BELOW floor 2×")
            vb_txt = "-" if rb is None else "meets target ≥ 3×" if rb >= 3 else "BELOW target 3×"
            summary += [
                f"{res}²  trace vs volprim fwd{vs}:   {'n/a' if tf is None else f'{tf:.2f}×'}",
                f"{res}²  raster vs volprim fwd{vs}:  {'n/a' if rf is None else f'{rf:.2f}×'}  [{vf_txt}]",
                f"{res}²  raster f+b vs trace f+b:  {'n/a' if rb is None else f'{rb:.2f}×'}  [{vb_txt}]"]
        if summary:
            print(flush=True)
            print("# ratios = time of the other / time of ours (> 1: ours faster)")
        for s in summary:
            print(s, flush=True)
        results["summary"] = summary
        if a.json:
            Path(a.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
