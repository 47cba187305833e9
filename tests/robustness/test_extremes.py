"""Extreme numerics across the stages, as one parametrised table of cases.

Each case builds a tiny input at an extreme (a 1e6 sun, an all-zero map, roughness 0/1,
metallic 1, grazing cameras, degenerate surfels, scenes at 1e-3 m and 1e3 m, cameras
inside objects, no surfels, probes with no neighbour, placements outside the scene) and
returns the arrays a stage produced. Contract: every returned array is finite, or the
case raises a clear ValueError that says what is wrong (``raises`` column) — never a
silent NaN in parameters or images. Scenes are 16 px and a few hundred surfels.
"""
import functools
import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import trimesh

from comgs_dr.core import octahedral as octa
from comgs_dr.core.cameras import perspective
from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels import SurfelParams
from comgs_dr.surfels.kernel import SH_C0

RES = 16


# --------------------------------------------------------------------- tiny inputs
def plane(n=12, half=1.0, z=0.0, grey=0.6) -> SurfelParams:
    """An opaque up-facing square of n x n surfels."""
    g = (np.arange(n) + 0.5) / n * 2 * half - half
    x, y = np.meshgrid(g, g)
    N = x.size
    return SurfelParams.from_numpy(
        means=np.stack([x.ravel(), y.ravel(), np.full(N, z)], -1),
        quats=np.tile([1.0, 0, 0, 0], (N, 1)), log_scales=np.full((N, 2), np.log(half / n)),
        opacity_logit=np.full(N, 5.0), sh=np.full((N, 1, 3), (grey - 0.5) / SH_C0),
        albedo=np.full((N, 3), grey), roughness=np.full(N, 0.5), metallic=np.zeros(N))


@functools.lru_cache(maxsize=None)
def _ball_numpy(n=300, r=0.3):
    from comgs_dr.surfels.from_mesh import from_mesh
    return from_mesh(trimesh.creation.icosphere(2, radius=r), n, opacity=0.98).to_numpy()


def ball(centre=(0, 0, 0.3), **materials) -> SurfelParams:
    d = {k: v.copy() for k, v in _ball_numpy().items()}
    d["means"] = d["means"] + np.asarray(centre)
    n = len(d["means"])
    for k, v in materials.items():
        d[k] = np.broadcast_to(np.asarray(v, np.float32), d[k].shape).copy()
    assert n > 0
    return SurfelParams.from_numpy(**d)


def concat(*ps) -> SurfelParams:
    return SurfelParams.concat(list(ps))


def scaled(p: SurfelParams, s: float) -> SurfelParams:
    d = p.to_numpy()
    d["means"] = d["means"] * s
    d["log_scales"] = d["log_scales"] + np.log(s)
    return SurfelParams.from_numpy(**d)


def sun_map(res=16, sun=1e6, sky=0.2):
    """Octahedral radiance: a constant sky and one ``sun`` texel (sun=0, sky=0: all zero)."""
    m = np.full((res, res, 3), sky)
    m[3, 5] = sun
    return m


def gbuffer(shapes: dict, eye, target=(0, 0, 0.2), res=RES, fov=45.0, clip=None,
            **props) -> dict:
    """{target: [H, W, C]} of the surfel_gbuffer integrator (``clip``: sensor clip planes)."""
    from comgs_dr.surfels.scene import gbuffer_scene
    sensor = {**perspective(eye, target, fov=fov, res=res), **(clip or {})}
    scene = gbuffer_scene(shapes, sensor, max_hits=16, **props)
    parts = scene.integrator().split(mi.render(scene))
    return {k: np.asarray(v) for k, v in parts.items()}


def sop_pbr(params: SurfelParams, radiance, eye, target=(0, 0, 0.2), rays=8,
            visibility="trace", extra_shapes=None, **props) -> dict:
    """{'image': [H, W, 3]} of the sop_pbr integrator lit by an ``octenvmap``."""
    from comgs_dr.emitters.octenvmap import OctEnvmapBase
    from comgs_dr.surfels.shape import SurfelShapeBase
    d = {"type": "scene", "env": OctEnvmapBase.from_radiance(radiance),
         "sensor": perspective(eye, target, fov=45.0, res=RES),
         "integrator": {"type": "sop_pbr", "visibility": visibility, "rays": rays,
                        "max_hits": 16, **props}}
    if params is not None:
        d["obj"] = SurfelShapeBase.from_params(params, id="obj")
    for k, v in (extra_shapes or {}).items():
        d[k] = SurfelShapeBase.from_params(v, id=k)
    with dr.suspend_grad():
        return {"image": np.asarray(mi.render(mi.load_dict(d), seed=3))}


# --------------------------------------------------------------------- cases: lighting
def env_emitter(radiance):
    """octenvmap: importance sampling (directions, pdf, weights) and evaluation."""
    from comgs_dr.emitters.octenvmap import OctEnvmapBase
    em = OctEnvmapBase.from_radiance(radiance)
    n = 4096
    u = to_jit(mi.Point2f, np.random.default_rng(0).random((2, n)))
    ds, w = em.sample_direction(dr.zeros(mi.Interaction3f), u)
    pdf = em.pdf_direction(dr.zeros(mi.Interaction3f), ds)
    ev = em.eval_direction(dr.zeros(mi.Interaction3f), ds)
    out = {"d": np.asarray(ds.d), "pdf": np.asarray(ds.pdf), "pdf_again": np.asarray(pdf),
           "weight": np.asarray(w), "eval": np.asarray(ev)}
    assert (out["pdf"] > 0).all(), "a sampled direction with zero density"
    return out


def learnable_env(radiance):
    """lighting.envmap.OctEnvmap: stored radiance, lookups, sampling, a refresh."""
    from comgs_dr.lighting.envmap import OctEnvmap
    env = OctEnvmap(radiance)
    u = to_jit(mi.Point2f, np.random.default_rng(1).random((2, 1024)))
    d, pdf = env.sample_world(u)
    env.refresh()
    return {"radiance": env.radiance_np(), "eval": np.asarray(env.eval(d)),
            "d": np.asarray(d), "pdf": np.asarray(pdf), "pdf_world": np.asarray(env.pdf_world(d))}


def irradiance_metrics(kind):
    """eval.lighting_metrics on equirect maps with a 1e6 sun and all zeros."""
    from comgs_dr.eval import lighting_metrics as lm
    sun = np.full((16, 32, 3), 0.1)
    sun[3, 7] = 1e6
    zero = np.zeros((16, 32, 3))
    est, gt = {"sun": (sun, sun), "zero": (zero, zero), "sun_vs_zero": (sun, zero),
               "zero_vs_sun": (zero, sun)}[kind]
    out = {"irradiance_up": np.array(lm.irradiance(est, [0, 0, 1])),
           "irradiance_down": np.array(lm.irradiance(est, [0, 0, -1]))}
    scores = lm.compare_maps(est, gt, size=16)
    out.update({k: np.array(v, np.float64) for k, v in _flatten(scores).items()
                if v is not None})
    return out


def _flatten(d, prefix=""):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        elif isinstance(v, (int, float, list, np.floating)):
            out[f"{prefix}{k}"] = v
    return out


def estimate_light_on(kind):
    """estimate-light on a tiny scene whose surfels radiate 1e6 (a sun) or nothing."""
    from comgs_dr.lighting import backends
    from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light
    from comgs_dr.surfels.scene import gbuffer_scene
    p = plane(n=16, half=2.0)
    d = p.to_numpy()
    if kind == "sun":
        d["sh"][:8, 0, :] = 1e6 / SH_C0              # a few blinding surfels
    else:
        d["sh"][:, 0, :] = -0.5 / SH_C0                # colour 0 everywhere
    scene = gbuffer_scene({"scene": SurfelParams.from_numpy(**d)}, [], targets="weight")
    r = estimate_light(scene, np.array([0.0, 0.0, 0.5]),
                       EstimateConfig(width=32, height=16, oct_res=8, max_hits=8),
                       backends.FillBackend("mean"))
    return {"hdr": r["hdr"], "oct": r["oct"], **{f"ldr{k}": v for k, v in r["ldrs"].items()}}


# --------------------------------------------------------------------- cases: materials
def brdf_extremes(roughness, metallic):
    """BRDF eval and GGX VNDF / cosine sampling at every direction class, including
    grazing (cos = 1e-7), normal incidence, below the horizon and wo = -wi."""
    from comgs_dr.shading import brdf
    rng = np.random.default_rng(2)
    dirs = [[0, 0, 1], [1, 0, 1e-7], [0, 1, -1e-7], [0, 0, -1], [1, 0, 0], [0.6, 0, 0.8],
            [-0.6, 0, 0.8]]
    dirs += list(rng.normal(size=(25, 3)))
    D = np.array([np.asarray(v, np.float64) / np.linalg.norm(v) for v in dirs])
    wo, wi = np.repeat(D, len(D), 0), np.tile(D, (len(D), 1))
    n = len(wo)
    V = lambda a: to_jit(mi.Vector3f, a.T)      # noqa: E731
    nz = mi.Vector3f(0, 0, 1)
    alb = mi.Color3f(0.9, 0.5, 0.1)
    r, m = to_jit(mi.Float, np.full(n, roughness)), to_jit(mi.Float, np.full(n, metallic))
    f = brdf.eval_brdf(alb, r, m, nz, V(wo), V(wi))
    alpha = brdf.ggx_alpha(mi.Float(roughness))
    corners = np.array([[0, 0], [0, 1], [1, 0], [1, 1], [0.5, 0.5], [1e-9, 1 - 1e-9]])
    u = np.concatenate([corners, rng.random((n - len(corners), 2))])
    us = to_jit(mi.Point2f, u.T)
    wi_s, pdf_s = brdf.sample_ggx_vndf(us, V(wo), alpha)
    wc, pc = brdf.sample_cosine_hemisphere(us)
    return {"f": np.asarray(f), "wi": np.asarray(wi_s), "pdf": np.asarray(pdf_s),
            "pdf_eval": np.asarray(brdf.pdf_ggx_vndf(V(wo), wi_s, alpha)),
            "cos_dir": np.asarray(wc), "cos_pdf": np.asarray(pc)}


def pbr_materials(roughness, metallic, sun, indirect=True):
    """sop_pbr through mi.render: a ball with extreme materials on a plane."""
    b = ball(roughness=roughness, metallic=metallic, albedo=(0.95, 0.9, 0.8))
    return sop_pbr(concat(plane(), b), sun_map(sun=sun, sky=0.0 if sun == 0 else 0.2),
                   eye=(1.5, -1.5, 1.2), sampling="mis", indirect=indirect)


# --------------------------------------------------------------------- cases: geometry
def grazing_camera(integrator):
    """A camera 0.1° above the plane of surfels, looking along it."""
    eye, target = (0.0, -3.0, 3.0 * np.tan(np.radians(0.1))), (0.0, 0.0, 0.0)
    if integrator == "gbuffer":
        return gbuffer({"s": plane()}, eye, target)
    return sop_pbr(plane(), sun_map(), eye, target)


def camera_inside(integrator):
    """The camera at the centre of a closed ball of surfels."""
    eye, target = (0.0, 0.0, 0.3), (1.0, 0.0, 0.3)
    if integrator == "gbuffer":
        return gbuffer({"b": ball()}, eye, target)
    return sop_pbr(ball(), sun_map(), eye, target)


def degenerate_surfels(kind):
    """Zero (log = -inf), vanishing (1e-30) or infinite scales, zero opacity, NaN
    parameters: the image stays finite and the bad surfels are counted, not silent."""
    from comgs_dr.surfels.shape import SurfelShapeBase
    d = plane().to_numpy()
    if kind == "zero_scale":
        d["log_scales"][::3] = -np.inf
    elif kind == "tiny_scale":
        d["log_scales"][::3] = np.log(1e-30)
    elif kind == "huge_scale":
        d["log_scales"][::7] = 80.0                  # e^80 ≈ 5e34
    elif kind == "zero_opacity":
        d["opacity_logit"][:] = -np.inf
    elif kind == "nan_means":
        d["means"][5] = np.nan
    elif kind == "nan_quat":
        d["quats"][7] = np.nan
    p = SurfelParams.from_numpy(**d)
    shape = SurfelShapeBase.from_params(p, id="s")
    out = gbuffer({"s": shape}, (0.5, -2.0, 2.0), (0, 0, 0))
    if kind.startswith("nan"):
        assert shape.nonfinite_count > 0, "non-finite surfels were not reported"
    return out


def load_nan_ply(tmp_path):
    """A PLY with NaN in a property is refused (clear error naming the property)."""
    import plyfile

    from comgs_dr.surfels import load_ply
    d = plane(n=3).to_numpy()
    cols = {"x": d["means"][:, 0], "y": d["means"][:, 1], "z": d["means"][:, 2],
            "f_dc_0": d["sh"][:, 0, 0], "f_dc_1": d["sh"][:, 0, 1], "f_dc_2": d["sh"][:, 0, 2],
            "opacity": d["opacity_logit"], "scale_0": d["log_scales"][:, 0],
            "scale_1": d["log_scales"][:, 1], **{f"rot_{i}": d["quats"][:, i] for i in range(4)}}
    cols["scale_1"] = cols["scale_1"].copy()
    cols["scale_1"][4] = np.nan
    arr = np.empty(9, [(k, "f4") for k in cols])
    for k, v in cols.items():
        arr[k] = v
    path = tmp_path / "nan.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(path))
    return {"params": load_ply(path).to_numpy()["log_scales"]}


def scene_scale(s):
    """The plane + ball scene and its camera scaled by s (1e-3 m .. 1e3 m), with the clip
    planes the stages use (``data.types.clip_planes`` of the scene's extent)."""
    from comgs_dr.data.types import clip_planes
    p = scaled(concat(plane(), ball()), s)
    out = gbuffer({"s": p}, np.array([1.5, -1.5, 1.2]) * s, np.array([0, 0, 0.2]) * s,
                  clip=clip_planes(3.0 * s))
    out["depth"] = out["depth"] / s                  # compare in scene units
    out["depth_unbiased"] = out["depth_unbiased"] / s
    return out


def empty_scene(integrator):
    """No surfel shape at all: the background / environment only."""
    if integrator == "gbuffer":
        return gbuffer({}, (0, -2, 1))
    return sop_pbr(None, sun_map(), (0, -2, 1))


def zero_surfels():
    """A surfels shape with no surfels is refused with a clear error."""
    from comgs_dr.surfels.shape import SurfelShapeBase
    empty = SurfelParams.from_numpy(means=np.zeros((0, 3)), quats=np.zeros((0, 4)),
                                    log_scales=np.zeros((0, 2)), opacity_logit=np.zeros(0),
                                    sh=np.zeros((0, 1, 3)))
    SurfelShapeBase.from_params(empty, id="nothing")
    return {}


# --------------------------------------------------------------------- cases: probes
def probe_query(kind):
    """Fixed-radius probe search at points with no neighbour, a single probe, coincident
    probes, points on a probe, points 1e30 away, a huge radius."""
    from comgs_dr.sops import query as q
    rng = np.random.default_rng(4)
    probes, radius = rng.uniform(-1, 1, (50, 3)), 0.2
    pts = rng.uniform(-1, 1, (64, 3))
    if kind == "no_neighbour":
        pts = pts + 10.0                                   # all far outside the radius
    elif kind == "single_probe":
        probes = probes[:1]
    elif kind == "coincident":
        probes = np.zeros((20, 3))
        pts[:8] = 0.0
    elif kind == "on_probe":
        pts[: len(probes)] = probes
    elif kind == "far_away":
        pts[:4] = [1e30, -1e30, 0]
    elif kind == "huge_radius":
        radius = 1e30
    elif kind == "tiny_radius":
        radius = 1e-46                                     # below float32
    grid = q.ProbeGrid(probes, radius)
    nrm = rng.normal(size=(len(pts), 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    res = q.query(grid, to_jit(mi.Point3f, pts.T), to_jit(mi.Vector3f, nrm.T), k=8)
    idx, w, count, fb = res.numpy()
    vals = q.interpolate(res, to_jit(mi.Float, np.arange(len(probes))))
    assert np.allclose(w.sum(1), 1.0, atol=1e-4), "weights do not sum to 1"
    assert (idx < len(probes)).all()
    if kind == "no_neighbour":
        assert fb.all() and (count == 0).all()
    return {"weight": w, "interp": np.asarray(vals)}


def probe_query_nan_point():
    """A NaN shading point is refused (the message counts them)."""
    from comgs_dr.sops import query as q
    grid = q.ProbeGrid(np.zeros((3, 3)) + [[0, 0, 0], [1, 0, 0], [0, 1, 0]], 0.5)
    q.query(grid, mi.Point3f([0.1, np.nan], [0, 0], [0, 0]), mi.Vector3f(0, 0, 1))
    return {}


# --------------------------------------------------------------------- cases: placement
def _camera(eye, target, res=RES):
    from comgs_dr.data.types import Camera
    s = perspective(eye, target, fov=45.0, res=res)
    return Camera(np.array(s["to_world"].matrix, np.float64), res, res, 45.0)


def placement_cameras_miss():
    """SOP placement when no camera sees the object: a clear error."""
    from comgs_dr.sops.placement import PlacementConfig, place_probes
    cams = [_camera((3 * np.cos(a), 3 * np.sin(a), 1.0), (30 * np.cos(a), 30 * np.sin(a), 1.0))
            for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]            # looking away
    place_probes(ball(), cams, PlacementConfig(count=50, max_views=4))
    return {}


def placement_normal():
    """SOP placement around a ball seen from 4 cameras (the reference for the cases)."""
    from comgs_dr.sops.placement import PlacementConfig, place_probes
    cams = [_camera((2 * np.cos(a), 2 * np.sin(a), 1.0), (0, 0, 0.3))
            for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    ps = place_probes(ball(), cams, PlacementConfig(count=50, max_views=4, min_consistent=1))
    return {"positions": ps.positions, "normals": ps.normals, "radius": np.array(ps.radius)}


def few_points_fps(n):
    """Farthest point sampling of fewer than 128 points (fpsample's KD-line needs 2^h <= n:
    it asserted for small fused point sets, e.g. a tiny object seen by few pixels)."""
    from comgs_dr.sops.placement import farthest_points
    pts = np.random.default_rng(5).normal(size=(n, 3))
    idx = farthest_points(pts, max(1, n // 3))
    assert len(np.unique(idx)) == len(idx) == max(1, n // 3) or n // 3 >= n
    return {"picked": pts[idx]}


def shadow_region_outside():
    """Shadow-region probes for an object placed 1 km outside the scene: a clear error."""
    from comgs_dr.sops import occlusion as occ
    d = plane().to_numpy()
    normals = np.tile([0.0, 0.0, 1.0], (len(d["means"]), 1))
    occ.shadow_region_probes(d["means"], normals, np.array([1000.0, 0, 0]),
                             np.array([1000.5, 0.5, 0.5]), occ.ShadowConfig(count=20, res=4))
    return {}


def _plane_scene_run(root, s: float):
    """A NeRF folder of 4 grey views around the origin and a step-1 scene run of a surfel
    plane, both scaled by ``s``: (data folder, run folder)."""
    import json

    from PIL import Image

    from comgs_dr.surfels import save_ply
    from comgs_dr.train.run import write_run_info
    data = root / "data"
    data.mkdir(parents=True)
    frames = []
    for i, a in enumerate(np.linspace(0, 2 * np.pi, 4, endpoint=False)):
        cam = _camera(np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 2.0]) * s, (0, 0, 0))
        Image.fromarray(np.full((RES, RES, 3), 128, np.uint8)).save(data / f"r_{i}.png")
        frames.append({"file_path": f"./r_{i}",
                       "transform_matrix": (cam.to_world @ np.diag([-1.0, 1, -1, 1])).tolist()})
    for split in ("train", "test"):
        (data / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": np.radians(45.0), "frames": frames}))
    run = root / "scene_run"
    write_run_info(run, data, "scene", 1, False)
    save_ply(scaled(plane(n=16, half=1.5), s), run / "point_cloud.ply")
    return data, run


def compose_outside(tmp_path):
    """``compose`` with an object placed 1 km outside the scene: a clear error naming the
    object, before any occlusion is traced."""
    from comgs_dr.core.similarity import Similarity, write_placements
    from comgs_dr.lighting import envmap as em
    from comgs_dr.sops import occlusion as occ
    from comgs_dr.sops.probes import ProbeSet
    from comgs_dr.stages.compose import ComposeConfig, compose
    from comgs_dr.surfels import save_ply
    data, run = _plane_scene_run(tmp_path, 1.0)
    obj = tmp_path / "obj"
    obj.mkdir()
    save_ply(ball((0, 0, 0)), obj / "point_cloud.ply")
    rng = np.random.default_rng(0)
    ProbeSet(rng.normal(size=(10, 3)) * 0.3, np.tile([0, 0, 1.0], (10, 1)), 4, 0.2,
             texture=rng.uniform(0, 1, (10, 4, 4, 4))).save(obj / "probes.npz")
    em.write_exr(tmp_path / "env.exr", sun_map(8, sun=50.0), "octahedral")
    write_placements(tmp_path / "t.json", {"chair": Similarity(1.0, np.eye(3),
                                                               np.array([1000.0, 0, 0.3]))})
    compose(run, {"chair": obj}, tmp_path / "t.json", tmp_path / "comp",
            env=tmp_path / "env.exr", progress=False,
            cfg=ComposeConfig(shadow=occ.ShadowConfig(count=20, res=4), scene_views=4,
                              min_consistent=1))
    return {}


# --------------------------------------------------------------------- the table
# (id, callable, expectation: see test_extreme); callables taking ``tmp_path`` get it.
CASES = [
    ("envmap-emitter-sun1e6", lambda: env_emitter(sun_map(sun=1e6)), None),
    ("envmap-emitter-zero", lambda: env_emitter(sun_map(sun=0.0, sky=0.0)), None),
    ("envmap-emitter-sun1e6-only", lambda: env_emitter(sun_map(sun=1e6, sky=0.0)), None),
    ("envmap-learnable-sun1e6", lambda: learnable_env(sun_map(sun=1e6)), None),
    ("envmap-learnable-zero", lambda: learnable_env(sun_map(sun=0.0, sky=0.0)), None),
    ("envmap-learnable-1e30", lambda: learnable_env(sun_map(sun=1e30)), None),
    ("irradiance-sun1e6", lambda: irradiance_metrics("sun"), None),
    ("irradiance-zero", lambda: irradiance_metrics("zero"), "either:zero|no energy|black|empty"),
    ("irradiance-sun-vs-zero", lambda: irradiance_metrics("sun_vs_zero"), "either:zero|no energy|black"),
    ("irradiance-zero-vs-sun", lambda: irradiance_metrics("zero_vs_sun"), "either:zero|no energy|black"),
    ("estimate-light-sun1e6", lambda: estimate_light_on("sun"), None),
    ("estimate-light-black", lambda: estimate_light_on("black"), None),
    ("brdf-r0-m0", lambda: brdf_extremes(0.0, 0.0), None),
    ("brdf-r0-m1", lambda: brdf_extremes(0.0, 1.0), None),
    ("brdf-r1-m0", lambda: brdf_extremes(1.0, 0.0), None),
    ("brdf-r1-m1", lambda: brdf_extremes(1.0, 1.0), None),
    ("sop_pbr-r0-m1-sun1e6", lambda: pbr_materials(0.0, 1.0, 1e6), None),
    ("sop_pbr-r1-m1-sun1e6", lambda: pbr_materials(1.0, 1.0, 1e6), None),
    ("sop_pbr-r0-m0-zero-map", lambda: pbr_materials(0.0, 0.0, 0.0), None),
    ("grazing-camera-gbuffer", lambda: grazing_camera("gbuffer"), None),
    ("grazing-camera-sop_pbr", lambda: grazing_camera("sop_pbr"), None),
    ("camera-inside-gbuffer", lambda: camera_inside("gbuffer"), None),
    ("camera-inside-sop_pbr", lambda: camera_inside("sop_pbr"), None),
    ("surfels-zero-scale", lambda: degenerate_surfels("zero_scale"), None),
    ("surfels-tiny-scale", lambda: degenerate_surfels("tiny_scale"), None),
    ("surfels-huge-scale", lambda: degenerate_surfels("huge_scale"), None),
    ("surfels-zero-opacity", lambda: degenerate_surfels("zero_opacity"), None),
    ("surfels-nan-means", lambda: degenerate_surfels("nan_means"), None),
    ("surfels-nan-quat", lambda: degenerate_surfels("nan_quat"), None),
    ("surfels-load-nan-ply", load_nan_ply, r"error:nan\.ply.*non-finite.*'scale_1'"),
    ("scene-1e-3m", lambda: scene_scale(1e-3), None),
    ("scene-1e3m", lambda: scene_scale(1e3), None),
    ("empty-scene-gbuffer", lambda: empty_scene("gbuffer"), "either:no 'surfels' shape"),
    ("empty-scene-sop_pbr", lambda: empty_scene("sop_pbr"), "either:no surfels shape"),
    ("zero-surfels", zero_surfels, "error:at least one surfel"),
    ("probes-no-neighbour", lambda: probe_query("no_neighbour"), None),
    ("probes-single", lambda: probe_query("single_probe"), None),
    ("probes-coincident", lambda: probe_query("coincident"), None),
    ("probes-point-on-probe", lambda: probe_query("on_probe"), None),
    ("probes-points-1e30-away", lambda: probe_query("far_away"), None),
    ("probes-radius-1e30", lambda: probe_query("huge_radius"), None),
    ("probes-radius-below-f32", lambda: probe_query("tiny_radius"), "error:radius.*underflows"),
    ("probes-nan-point", probe_query_nan_point, "error:not finite"),
    ("placement-normal", placement_normal, None),
    ("placement-cameras-miss", placement_cameras_miss, "error:kept no point"),
    ("placement-fps-2-points", lambda: few_points_fps(2), None),
    ("placement-fps-5-points", lambda: few_points_fps(5), None),
    ("placement-fps-100-points", lambda: few_points_fps(100), None),
    ("placement-shadow-region-outside", shadow_region_outside, "error:no scene surface point"),
    ("compose-object-outside-scene", compose_outside, "error:'chair'.*placement|placement.*'chair'"),
]


def _call(fn, tmp_path):
    import inspect
    return fn(tmp_path) if inspect.signature(fn).parameters else fn()


@pytest.mark.parametrize("fn,expect", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_extreme(fn, expect, tmp_path):
    """``expect``: None (finite outputs), "error:<regex>" (a ValueError matching it) or
    "either:<regex>" (finite outputs or such an error)."""
    kind, _, pattern = (expect or "finite:").partition(":")
    try:
        out = _call(fn, tmp_path)
    except Exception as e:  # noqa: BLE001 - mi.render wraps a plugin's ValueError
        value_error = _value_error(e)
        assert value_error is not None, f"not a ValueError: {type(e).__name__}: {e}"
        assert kind in ("error", "either"), f"unexpected error: {value_error}"
        assert re.search(pattern, str(value_error), re.S), f"unclear message: {value_error}"
        return
    assert kind != "error", f"accepted without the expected error ({pattern})"
    _check_finite(out)


def _value_error(e):
    """``e`` or the ValueError it wraps (Mitsuba re-raises plugin errors as RuntimeError)."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, ValueError):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


def _check_finite(out: dict) -> None:
    for k, v in out.items():
        a = np.asarray(v)
        assert a.dtype.kind not in "fc" or np.isfinite(a).all(), \
            f"silent non-finite output {k!r} ({int((~np.isfinite(a)).sum())} of {a.size})"


def test_scaled_scenes_render_alike():
    """The same scene at 1e-3 m, 1 m and 1e3 m (camera scaled with it): the same image."""
    ref = scene_scale(1.0)
    assert ref["weight"].max() > 0.9
    for s in (1e-3, 1e3):
        other = scene_scale(s)
        for key in ("weight", "color", "normal"):
            diff = np.abs(other[key] - ref[key])
            assert diff.mean() < 0.02, (s, key, diff.mean())
        cov = (ref["weight"][..., 0] > 0.99) & (other["weight"][..., 0] > 0.99)
        assert np.allclose(other["depth"][cov], ref["depth"][cov], rtol=1e-2), s


def test_extreme_materials_are_bounded():
    """The 1e6 sun on a mirror-like metal: bright but finite, no pixel negative; an
    all-zero map without indirect light renders black (exp(-16) floor of the log map)."""
    img = pbr_materials(0.0, 1.0, 1e6)["image"]
    assert np.isfinite(img).all() and img.min() >= 0 and img.max() > 1.0
    dark = pbr_materials(0.0, 0.0, 0.0, indirect=False)["image"]
    assert np.isfinite(dark).all() and 0.0 <= dark.min() and dark.max() < 1e-5


def test_sun_sampling_finds_the_sun():
    """Importance sampling a 1e6 sun texel: nearly all samples land in it or its 3x3
    neighbourhood (the sampler weights texels by the 3x3 maximum, as bilinear lookups
    spread the sun), weights finite and bounded."""
    rad = sun_map(sun=1e6)
    out = env_emitter(rad)
    uv = octa.dir_to_uv_np(out["d"].T if out["d"].shape[0] == 3 else out["d"])
    t = np.floor(uv * 16).astype(int).clip(0, 15)
    frac = np.mean((np.abs(t[:, 1] - 3) <= 1) & (np.abs(t[:, 0] - 5) <= 1))
    assert frac > 0.99, frac
    assert np.isfinite(out["weight"]).all() and out["weight"].max() < 1e7


def _scaled_run(root, s):
    """A NeRF-synthetic capture (3 cameras looking down at the plane + ball) and a finished
    step-1 run of that scene, everything scaled by ``s``."""
    import json

    from PIL import Image

    from comgs_dr.surfels import save_ply
    from comgs_dr.train.run import write_run_info
    data = root / "data"
    data.mkdir(parents=True)
    docs = {"train": [], "test": []}
    for i, a in enumerate(np.linspace(0, 2 * np.pi, 3, endpoint=False)):
        cam = _camera(np.array([2 * np.cos(a), 2 * np.sin(a), 1.5]) * s, np.array([0, 0, 0.2]) * s)
        Image.fromarray(np.full((RES, RES, 3), 90, np.uint8)).save(data / f"r_{i}.png")
        gl = cam.to_world @ np.diag([-1.0, 1, -1, 1])           # Mitsuba -> OpenGL camera axes
        docs["test" if i == 0 else "train"].append({"file_path": f"./r_{i}",
                                                     "transform_matrix": gl.tolist()})
    for split, frames in docs.items():
        (data / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": np.radians(45.0), "frames": frames}))
    run = root / "run"
    write_run_info(run, data, "object", 1, False)
    save_ply(scaled(concat(plane(), ball()), s), run / "point_cloud.ply")
    return run


def test_stages_at_1e_3_and_1e3_metres(tmp_path):
    """``comgs render`` and SOP placement on the same capture at 1 mm, 1 m and 1 km scale:
    the same images and the same probes (scaled). Before the clip planes followed the
    scene's size, the 1 mm scene rendered empty (Mitsuba's absolute near clip of 1 cm)."""
    from PIL import Image

    from comgs_dr.sops.placement import PlacementConfig, place_probes
    from comgs_dr.stages.render_run import render_run
    imgs, probes = {}, {}
    for s in (1.0, 1e-3, 1e3):
        run = _scaled_run(tmp_path / f"s{s:g}", s)
        m = render_run(run, "test", progress=False)
        assert np.isfinite(m["psnr"]), s
        imgs[s] = np.asarray(Image.open(run / "render_test" / "000_color.png"), np.float64)
        cams = [_camera(np.array([2 * np.cos(a), 2 * np.sin(a), 1.5]) * s, np.array([0, 0, .2]) * s)
                for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
        ps = place_probes(scaled(ball(), s), cams, PlacementConfig(count=30, max_views=4,
                                                                    min_consistent=1))
        probes[s] = ps.positions / s
    assert imgs[1.0].std() > 5                                 # the scene is in view
    for s in (1e-3, 1e3):
        assert np.abs(imgs[s] - imgs[1.0]).mean() < 1.0, s     # 8-bit levels
        assert np.allclose(probes[s], probes[1.0], atol=1e-3), s


def _composition(root, s):
    """A scene run (plane), an object run (ball + probes), a placement on the plane and
    ``compose`` + ``render-comp`` (sop), all scaled by ``s``; the rendered test frame."""

    from PIL import Image

    from comgs_dr.core.similarity import Similarity, write_placements
    from comgs_dr.lighting import envmap as em
    from comgs_dr.sops import occlusion as occ
    from comgs_dr.sops.bake import bake
    from comgs_dr.sops.probes import ProbeSet
    from comgs_dr.stages.compose import ComposeConfig, compose
    from comgs_dr.stages.render_comp import render_comp
    from comgs_dr.surfels import save_ply
    from comgs_dr.surfels.shape import SurfelShapeBase
    data, run = _plane_scene_run(root, s)
    obj = root / "obj"
    obj.mkdir()
    b = scaled(ball((0, 0, 0)), s)
    save_ply(b, obj / "point_cloud.ply")
    g = np.linspace(-0.3, 0.3, 3) * s
    pos = np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3)
    probes = ProbeSet(pos, np.tile([0, 0, 1.0], (len(pos), 1)), 4, 0.4 * s)
    bake(mi.load_dict({"type": "scene", "o": SurfelShapeBase.from_params(b, id="o")}), probes,
         max_hits=8, progress=False)
    probes.save(obj / "probes.npz")
    em.write_exr(root / "env.exr", sun_map(8, sun=50.0), "octahedral")
    write_placements(root / "t.json", {"ball": Similarity(1.0, np.eye(3),
                                                          np.array([0, 0, 0.3]) * s)})
    compose(run, {"ball": obj}, root / "t.json", root / "comp", env=root / "env.exr",
            progress=False, cfg=ComposeConfig(shadow=occ.ShadowConfig(count=30, res=4),
                                              scene_views=4, min_consistent=1))
    m = render_comp(root / "comp", data / "transforms_test.json", "sop", res=RES, rays=8,
                    progress=False)
    assert m["frames"] == 4
    return np.asarray(Image.open(root / "comp" / "renders" / "sop" / "r_1.png"), np.float64)


def test_composition_at_1e_3_metres(tmp_path):
    """``compose`` + ``render-comp`` of the same composition at 1 m and 1 mm: the same
    frame (the 1 mm one was clipped away by the sensor's absolute near plane)."""
    ref = _composition(tmp_path / "m", 1.0)
    small = _composition(tmp_path / "mm", 1e-3)
    assert ref.std() > 5
    assert np.abs(small - ref).mean() < 2.0, np.abs(small - ref).mean()


def test_decompose_at_1e_3_metres(tmp_path):
    """Step 2 (a few iterations) on the same capture at 1 m and 1 mm: both train."""
    from comgs_dr.stages.decompose import MaterialConfig, train_material
    cfg = MaterialConfig(iterations=3, rays=4, probe_count=40, env_res=8, eval_every=3,
                         eval_views=1, log_every=1, checkpoint_every=100)
    scores = {}
    for s in (1.0, 1e-3):
        r = train_material(_scaled_run(tmp_path / f"s{s:g}", s), None, cfg, progress=False)
        scores[s] = r["psnr_test"]
    assert np.isfinite(scores[1e-3]) and abs(scores[1e-3] - scores[1.0]) < 0.5, scores


def test_export_mesh_at_1e_3_metres(tmp_path):
    """``export-mesh`` (TSDF) of the same capture at 1 m and 1 mm: the same surface, scaled
    (the 1 mm run found 'no surface in the volume': its views were clipped away)."""
    from comgs_dr.stages.export_mesh import MeshConfig, export_mesh
    verts = {}
    for s in (1.0, 1e-3):
        out = tmp_path / f"m{s:g}.ply"
        r = export_mesh(_scaled_run(tmp_path / f"s{s:g}", s), out,
                        MeshConfig(method="tsdf", resolution=32), progress=False)
        verts[s] = (r["vertices"], np.ptp(trimesh.load(out).vertices, axis=0) / s)
    assert abs(verts[1e-3][0] - verts[1.0][0]) < 0.05 * verts[1.0][0], verts
    assert np.allclose(verts[1e-3][1], verts[1.0][1], rtol=0.05), verts
