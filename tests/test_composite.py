"""Composition: shadow ratio, occlusion caching, the comgs_composite integrator (through
mi.render), the compose stage's cache."""
import json

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import trimesh
from PIL import Image
from conftest import error_chain_text

from comgs_dr.core import octahedral as octa
from comgs_dr.core.cameras import perspective
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.similarity import Similarity, euler_xyz_deg, write_placements
from comgs_dr.emitters.octenvmap import OctEnvmapBase
from comgs_dr.surfels.params import object_bounds
from comgs_dr.lighting import envmap as em
from comgs_dr.shading.shadow import shadow_ratio
from comgs_dr.shading.visibility import NoVisibility
from comgs_dr.sops import occlusion as occ
from comgs_dr.sops.bake import bake
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.surfels.from_mesh import from_mesh
from comgs_dr.surfels.groups import group_gbuffer
from comgs_dr.surfels.io import save_ply
from comgs_dr.surfels.params import SurfelParams
from comgs_dr.surfels.shape import SurfelShapeBase

SUN = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])


def plane(n=40, half=2.0, grey=0.6, z=0.0):
    """A grid of opaque up-facing surfels (the 'scene')."""
    g = (np.arange(n) + 0.5) / n * 2 * half - half
    x, y = np.meshgrid(g, g)
    N = x.size
    sh = np.zeros((N, 1, 3))
    sh[:, 0, :] = (grey - 0.5) / 0.28209479
    return SurfelParams.from_numpy(np.stack([x.ravel(), y.ravel(), np.full(N, z)], -1),
                                   np.tile([1.0, 0, 0, 0], (N, 1)),
                                   np.full((N, 2), np.log(2 * half / n * 0.9)), np.full(N, 6.0), sh)


def ball(centre, r=0.4, albedo=(0.8, 0.3, 0.2), n=1200):
    p = from_mesh(trimesh.creation.icosphere(3, radius=r), n, opacity=0.98, roughness=0.6)
    d = p.to_numpy()
    d["means"] = d["means"] + np.asarray(centre)
    d["albedo"][:] = albedo
    return SurfelParams.from_numpy(**d)


def sun_map(res=64, sky=0.3, sun=2000.0, direction=SUN):
    """Octahedral map: a constant sky and a small sun at ``direction``."""
    d = octa.texel_directions_np(res).reshape(res, res, 3)
    m = np.full((res, res, 3), sky)
    m[(d @ np.asarray(direction)) > np.cos(np.radians(4.0))] = sun
    return m


def scene_of(shapes, integrator, res=40, eye=(3.0, -3.0, 2.6), target=(0, 0, 0.3)):
    d = {"type": "scene", "integrator": integrator,
         "sensor": perspective(eye, target, fov=40, res=res)}
    for k, p in shapes.items():
        d[k] = SurfelShapeBase.from_params(p, id=k)
    return mi.load_dict(d)


class ConeBlocker:
    """O = 1 inside a cone around ``axis`` (an occluder blocking exactly the sun)."""
    name = "cone"

    def __init__(self, axis, half_deg):
        self.axis, self.cos = axis, float(np.cos(np.radians(half_deg)))

    def prepare(self, pts):
        pass

    def lookup(self, pid, wi, need_radiance):
        a = mi.Vector3f(*map(float, self.axis))
        return dr.select(dr.dot(wi, a) > self.cos, 1.0, 0.0), None


def test_shadow_ratio_one_without_occluder_and_ambient_fraction_when_sun_blocked():
    res = 64
    m = sun_map(res)
    env = OctEnvmapBase.from_radiance(m)
    n = 64
    x = to_jit(mi.Point3f, np.zeros((3, n)))
    nz = to_jit(mi.Vector3f, np.stack([np.zeros(n), np.zeros(n), np.ones(n)]))
    S0 = np.asarray(shadow_ratio(x, nz, env, NoVisibility(), rays=64))
    assert np.all(S0 == 1.0)
    # reference: texel sums over the map of L · cos⁺ · solid angle, sun cone removed
    d = octa.texel_directions_np(res)
    w = octa.texel_solid_angles_np(res).ravel() * np.maximum(d[:, 2], 0)
    L = m.reshape(-1, 3)[:, 0]
    blocked = (d @ SUN) > np.cos(np.radians(6.0))
    want = (w * L * ~blocked).sum() / (w * L).sum()
    assert want < 0.5                                   # the sun dominates: a real shadow
    S = np.asarray(shadow_ratio(x, nz, env, ConeBlocker(SUN, 6.0), rays=1024))
    assert np.all((S >= 0) & (S <= 1))
    assert abs(S.mean() - want) < 0.03, (S.mean(), want)
    full = np.asarray(shadow_ratio(x, nz, env, ConeBlocker(SUN, 179.9), rays=64))
    assert np.all(full == 0.0)


def test_transform_probes_resamples_directions():
    res = 16
    d = octa.texel_directions_np(res)
    f = lambda v: 0.5 + 0.3 * v[:, 0] + 0.2 * v[:, 2]             # noqa: E731  smooth in ω
    tex = np.zeros((1, res, res, 4), np.float32)
    tex[0, ..., 3] = f(d).reshape(res, res)
    pr = ProbeSet(np.zeros((1, 3)), [[0, 0, 1.0]], res, 0.1, texture=tex)
    R = euler_xyz_deg(0, 0, 90)
    out = occ.transform_probes(pr, Similarity(2.0, R, np.array([1.0, 0, 0])))
    want = f(d @ R).reshape(res, res)                             # f(Rᵀ ω)
    assert np.abs(out.texture[0, ..., 3] - want).max() < 0.03
    np.testing.assert_allclose(out.positions[0], [1, 0, 0], atol=1e-6)
    assert out.radius == pytest.approx(0.2)


def _probes_for(params, res=8, count=200, offset=0.02, bake_scene=None):
    """SOPs on an object's surface, baked against ``bake_scene`` (default: itself)."""
    m = np.asarray(params.means).T if np.asarray(params.means).shape[0] == 3 else np.asarray(params.means)
    c = m.mean(0)
    nrm = (m - c) / np.linalg.norm(m - c, axis=1, keepdims=True)
    idx = np.linspace(0, len(m) - 1, count).astype(int)
    pr = ProbeSet(m[idx] + offset * nrm[idx], nrm[idx], res, 0.25)
    sc = bake_scene or mi.load_dict({"type": "scene", "o": SurfelShapeBase.from_params(params)})
    return bake(sc, pr, progress=False)


def _shadow_probes(scene_p, objects, res=16, count=1500):
    pts = np.asarray(scene_p.means)
    pts = pts.T if pts.shape[0] == 3 else pts
    nrm = np.tile([0, 0, 1.0], (len(pts), 1))
    occ_scene = mi.load_dict({"type": "scene", **{k: SurfelShapeBase.from_params(p, id=k)
                                                   for k, p in objects.items()}})
    parts = []
    for k, p in objects.items():
        m = np.asarray(p.means)
        m = m.T if m.shape[0] == 3 else m
        ps = occ.shadow_region_probes(pts, nrm, m.min(0), m.max(0),
                                      occ.ShadowConfig(count=count, res=res, supersample=2))
        ps.texture = np.zeros((ps.count, res, res, 4), np.float32)
        ps.texture[..., 3] = occ.trace_occlusion(ps, occ_scene, supersample=2)
        parts.append(ps)
    return ProbeSet(np.concatenate([p.positions for p in parts]),
                    np.concatenate([p.normals for p in parts]), res,
                    max(p.radius for p in parts),
                    texture=np.concatenate([p.texture for p in parts]))


@pytest.fixture(scope="module")
def sphere_over_plane(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("comp")
    em.write_exr(tmp / "env.exr", sun_map(), "octahedral")
    scene_p, b = plane(), ball((0.0, 0.0, 0.7))
    _shadow_probes(scene_p, {"ball": b}).save(tmp / "shadow.npz")
    _probes_for(b).save(tmp / "ball.npz")
    return tmp, scene_p, b


def _render(tmp, shapes, variant, res=40, env="env.exr", eye=(3.0, -3.0, 2.6), **kw):
    integ = {"type": "comgs_composite", "variant": variant, "envmap": str(tmp / env),
             "rays": 64, "shadow_rays": 128, **kw}
    if variant == "sop" and "shadow_probes" not in kw:
        integ["shadow_probes"] = str(tmp / "shadow.npz")
    sc = scene_of(shapes, integ, res, eye)
    return np.asarray(mi.render(sc, seed=3)), sc


def test_sop_shadows_match_traced_shadows(sphere_over_plane):
    tmp, scene_p, b = sphere_over_plane
    shapes = {"scene": scene_p, "ball": b}
    sop, sc = _render(tmp, shapes, "sop", probes_ball=str(tmp / "ball.npz"))
    tr, _ = _render(tmp, shapes, "trace")
    none, _ = _render(tmp, shapes, "noshadow", probes_ball=str(tmp / "ball.npz"))
    assert all(np.isfinite(a).all() for a in (sop, tr, none))
    with pytest.raises(ValueError, match="groups given for \\['ball'\\]"):
        group_gbuffer(sc, sc.sensors()[0], {"ball": 0})
    buf = group_gbuffer(sc, sc.sensors()[0], {"scene": 0, "ball": 1})
    ground = (np.asarray(buf.weight[0]) > 0.99).reshape(40, 40)
    lum = lambda a: a[..., :3].mean(-1)                         # noqa: E731
    dark_tr = ground & (lum(tr) < 0.6 * lum(none))              # the traced shadow
    assert dark_tr.sum() >= 10                                  # a real shadow in view
    dark_sop = ground & (lum(sop) < 0.6 * lum(none))
    iou = (dark_tr & dark_sop).sum() / (dark_tr | dark_sop).sum()
    assert iou > 0.7, iou
    err = np.abs(lum(sop) - lum(tr))[ground].mean() / lum(none)[ground].mean()
    assert err < 0.05, err                                      # stated: < 5 % mean abs.
    # the probes alone (no traced sun rays): the same shadow within 5 %, but further from
    # the traced one than with the sun's rays traced
    plain, _ = _render(tmp, shapes, "sop", probes_ball=str(tmp / "ball.npz"), sun_rays=0)
    err_plain = np.abs(lum(plain) - lum(tr))[ground].mean() / lum(none)[ground].mean()
    assert err_plain < 0.05, err_plain
    assert err < err_plain, (err, err_plain)
    # the sun's rays looking up its shadow map (the default) or traced per pixel: the same
    # shadow (the map's texels are ≤ 1/256 of the objects' size)
    per_px, _ = _render(tmp, shapes, "sop", probes_ball=str(tmp / "ball.npz"), sun_map_res=0)
    err_px = np.abs(lum(per_px) - lum(tr))[ground].mean() / lum(none)[ground].mean()
    assert err_px < err_plain, (err_px, err_plain)
    diff = np.abs(lum(per_px) - lum(sop))[ground].mean() / lum(none)[ground].mean()
    assert diff < 0.01, diff
    # no shadow pass outside the shadow region (here 2× the ball's bounds): the ground
    # there is exactly the unshadowed scene
    small, _ = _render(tmp, shapes, "trace", region_factor=2.0)
    x = np.asarray(buf.points(0, dr.arange(mi.UInt32, 1600))[0]).T.reshape(40, 40, 3)
    lo, hi = object_bounds(b)
    c, half = (lo + hi) / 2, (hi - lo)
    out = ground & np.any(np.abs(x - c) > half * 1.01, axis=-1)
    assert out.sum() > 0.3 * ground.sum()
    np.testing.assert_array_equal(small[out], none[out])
    assert np.abs(small - none)[~out].max() > 0.1        # the shadow itself is inside


def test_depth_compositing_at_an_occlusion_boundary(sphere_over_plane):
    tmp, _, b = sphere_over_plane
    # a vertical scene wall between the camera and the right half of the ball
    wall = plane(n=30, half=0.6, grey=0.2).to_numpy()
    m = wall["means"]
    wall["means"] = np.stack([m[:, 0] + 0.6, np.full(len(m), -1.0), m[:, 1] + 0.7], -1)
    wall["quats"][:] = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0]    # normal along -y
    wall = SurfelParams.from_numpy(**wall)
    img, sc = _render(tmp, {"scene": wall, "ball": b}, "paste")
    buf = group_gbuffer(sc, sc.sensors()[0], {"scene": 0, "ball": 1})
    Wb = np.asarray(buf.weight[1]).reshape(40, 40)
    Ws = np.asarray(buf.weight[0]).reshape(40, 40)
    assert np.all(Wb + Ws <= 1.0 + 1e-5)
    # where the wall is in front (covers the pixel) the ball does not show
    front = Ws > 0.99
    assert front.sum() > 20 and Wb[front].max() < 0.01
    # the ball is visible elsewhere, with partial (antialiased) coverage at its edges
    assert (Wb > 0.9).sum() > 20
    edge = (Wb > 0.05) & (Wb < 0.9)
    assert edge.sum() > 5
    # the image there is the coverage-weighted blend of the layers
    grey = (0.2 - 0.5) / 0.28209479 * 0.28209479 + 0.5
    assert np.all(np.abs(img[front].mean(-1) - grey ** 2.2) < 0.02)


def test_two_objects_shadow_each_other(sphere_over_plane):
    tmp, scene_p, _ = sphere_over_plane
    a, b = ball((-0.45, 0.0, 0.45), 0.35), ball((0.45, 0.0, 0.45), 0.35, (0.2, 0.6, 0.9))
    both = mi.load_dict({"type": "scene", "a": SurfelShapeBase.from_params(a, id="a"),
                         "b": SurfelShapeBase.from_params(b, id="b")})
    sp = _shadow_probes(scene_p, {"a": a, "b": b}, count=400)
    sp.save(tmp / "shadow2.npz")
    only_a = mi.load_dict({"type": "scene", "a": SurfelShapeBase.from_params(a, id="a")})
    pb = _probes_for(b)                            # b's own probes (self-occlusion)
    o_by_a = occ.trace_occlusion(pb, only_a, supersample=1)
    assert o_by_a.max() > 0.9                      # a blocks part of b's sky
    # b's probes with a's occlusion combined, as compose writes them
    tex = pb.texture.copy()
    tex[..., 3] = occ.combine([tex[..., 3], o_by_a])
    ProbeSet(pb.positions, pb.normals, pb.res, pb.radius, texture=tex).save(tmp / "b.npz")
    pb.save(tmp / "b_alone.npz")
    _probes_for(a).save(tmp / "a.npz")
    shapes = {"scene": scene_p, "a": a, "b": b}
    low = np.array([-np.cos(np.radians(35)), 0.0, np.sin(np.radians(35))])   # sun from −x
    em.write_exr(tmp / "low.exr", sun_map(direction=low), "octahedral")
    kw = dict(shadow_probes=str(tmp / "shadow2.npz"), probes_a=str(tmp / "a.npz"),
              env="low.exr", eye=(0.0, -4.0, 2.0))
    with_a, sc = _render(tmp, shapes, "sop", probes_b=str(tmp / "b.npz"), **kw)
    without, _ = _render(tmp, shapes, "sop", probes_b=str(tmp / "b_alone.npz"), **kw)
    buf = group_gbuffer(sc, sc.sensors()[0], {"scene": 0, "a": 1, "b": 2})
    Wb = np.asarray(buf.weight[2]).reshape(40, 40) > 0.9
    assert with_a[Wb].mean() < 0.9 * without[Wb].mean()       # a's shadow on b
    # each object casts its shadow on the ground: a's between the two, b's beyond b
    none, _ = _render(tmp, shapes, "noshadow", probes_a=str(tmp / "a.npz"),
                      probes_b=str(tmp / "b.npz"), env="low.exr", eye=(0.0, -4.0, 2.0))
    ground = np.asarray(buf.weight[0]).reshape(40, 40) > 0.99
    dark = ground & (with_a.mean(-1) < 0.6 * none.mean(-1))
    x = np.asarray(buf.points(0, dr.arange(mi.UInt32, 1600))[0]).T.reshape(40, 40, 3)
    assert (dark & (x[..., 0] > -0.2) & (x[..., 0] < 0.5)).sum() >= 3
    assert (dark & (x[..., 0] > 0.8)).sum() >= 3


def test_composite_gradient_wrt_object_albedo_matches_finite_differences(sphere_over_plane):
    tmp, scene_p, b = sphere_over_plane
    integ = {"type": "comgs_composite", "variant": "noshadow", "envmap": str(tmp / "env.exr"),
             "rays": 32, "sampling": "uniform", "probes_ball": str(tmp / "ball.npz")}
    sc = scene_of({"scene": scene_p, "ball": b}, integ, res=24)
    params = mi.traverse(sc)
    key = "ball.albedo"
    a0 = mi.Color3f(params[key])
    rng = np.random.default_rng(0)
    v = to_jit(mi.Color3f, rng.uniform(-1, 1, (3, dr.width(a0))).astype(np.float32))
    wimg = to_jit(mi.TensorXf, rng.uniform(0, 1, (24, 24, 3)).astype(np.float32))

    def loss(alb, grad=False):
        params[key] = alb
        params.update()
        if grad:
            dr.enable_grad(params[key])
        img = mi.render(sc, params, seed=5, seed_grad=6)
        val = dr.sum(img * wimg, axis=None)
        if grad:
            dr.backward(val)
            gr = np.asarray(dr.grad(params[key]))
            return float((gr * np.asarray(v)).sum())
        return float(np.asarray(val).ravel()[0])
    h = 1e-2
    g = loss(mi.Color3f(a0), grad=True)
    fd = (loss(a0 + h * v) - loss(a0 - h * v)) / (2 * h)
    assert abs(g) > 1e-3
    assert g == pytest.approx(fd, rel=2e-2), (g, fd)


@pytest.mark.parametrize("key,bound", [("metallic", 0.0), ("roughness", 1.0)])
def test_composite_gradient_at_a_material_bound(sphere_over_plane, key, bound):
    """Step 2 clamps materials to their bounds after every step (its PLY holds metallic 0
    and roughness 1 exactly): the gradient there is the one-sided derivative into the
    range, not 0 (``kernel.clamp_closed``)."""
    tmp, scene_p, b = sphere_over_plane
    # a smooth sky (uniform sampling): the primal and the gradient pass take different
    # samples, and under the small sun their estimates differ by more than the tolerance
    d = octa.texel_directions_np(32).reshape(32, 32, 3)
    em.write_exr(tmp / "smooth.exr", 0.5 + np.clip(d @ [0.6, -0.3, 0.74], 0, None)[..., None]
                 * [3.0, 2.5, 2.0], "octahedral")
    integ = {"type": "comgs_composite", "variant": "noshadow", "envmap": str(tmp / "smooth.exr"),
             "rays": 64, "sampling": "uniform", "probes_ball": str(tmp / "ball.npz")}
    sc = scene_of({"scene": scene_p, "ball": b}, integ, res=24)
    params = mi.traverse(sc)
    name = f"ball.{key}"
    n = dr.width(params[name])
    wimg = to_jit(mi.TensorXf, np.random.default_rng(1).uniform(0, 1, (24, 24, 3)).astype(np.float32))
    inward = -1.0 if bound == 1.0 else 1.0

    def loss(value, grad=False):
        params[name] = dr.full(mi.Float, value, n)
        params.update()
        if grad:
            dr.enable_grad(params[name])
        val = dr.sum(mi.render(sc, params, seed=5, seed_grad=6) * wimg, axis=None)
        if grad:
            dr.backward(val)
            return float(dr.sum(dr.grad(params[name]))[0]) * inward
        return float(np.asarray(val).ravel()[0])
    h = 1e-2
    g = loss(bound, grad=True)
    fd = (loss(bound + inward * h) - loss(bound)) / h          # one-sided, into the range
    assert abs(fd) > 1e-3 and g == pytest.approx(fd, rel=5e-2), (g, fd)


def _nerf_folder(root, n=4, res=24):
    """A minimal NeRF-synthetic capture (cameras around the origin, flat images)."""
    root.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        az = 2 * np.pi * i / n
        eye = np.array([3 * np.cos(az), 3 * np.sin(az), 2.5])
        f = -eye / np.linalg.norm(eye)
        r = np.cross(f, [0, 0, 1.0])
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, u, -f, eye
        Image.fromarray(np.full((res, res, 3), 128, np.uint8)).save(root / f"r_{i}.png")
        frames.append({"file_path": f"./r_{i}", "transform_matrix": m.tolist()})
    doc = {"camera_angle_x": np.radians(45.0), "frames": frames}
    for split in ("train", "test"):
        (root / f"transforms_{split}.json").write_text(json.dumps(doc))
    return root


def scene_run(root, res, plane_n):
    """``root/scene_run``: a step-1 run of a plane (``plane_n``²) whose dataset is a NeRF
    capture of 4 flat views at ``res`` px in ``root/data``; returns the run folder."""
    from comgs_dr.surfels.io import save_ply
    from comgs_dr.train.run import write_run_info
    data = _nerf_folder(root / "data", res=res)
    run = root / "scene_run"
    write_run_info(run, data, "scene", 1, False)
    save_ply(plane(n=plane_n), str(run / "point_cloud.ply"))
    return run


def object_run(folder, r, albedo, probes):
    """``folder``: an object run of a ball (radius ``r``, 300 surfels) with ``probes``
    SOPs; returns the folder."""
    from comgs_dr.surfels.io import save_ply
    p = ball((0, 0, 0), r, albedo, n=300)
    folder.mkdir()
    save_ply(p, str(folder / "point_cloud.ply"))
    _probes_for(p, count=probes).save(folder / "probes.npz")
    return folder


def tiny_composition(tmp, res, placements=(("t", 0.2),)):
    """A scene run (a plane), an object run ``a`` (a ball + probes), a sun map ``env.exr``, a
    NeRF capture of 4 flat views at ``res`` px (``data/``), one placements file per
    (name, x) of ``placements`` and the composition of the first in ``tmp/comp``: the
    small composition the render-comp, camera-path and batch tests share."""
    from comgs_dr.core.similarity import Similarity, write_placements
    from comgs_dr.lighting import envmap as em
    from comgs_dr.sops import occlusion as occ
    from comgs_dr.stages.compose import ComposeConfig, compose
    run = scene_run(tmp, res, 20)
    object_run(tmp / "a", 0.3, (0.8, 0.2, 0.2), 40)
    em.write_exr(tmp / "env.exr", sun_map(16), "octahedral")
    for name, x in placements:
        write_placements(tmp / f"{name}.json",
                         {"a": Similarity(1.0, np.eye(3), np.array([x, 0, 0.3]))})
    cfg = ComposeConfig(shadow=occ.ShadowConfig(count=100, res=8, supersample=1),
                        scene_views=4, min_consistent=1)
    compose(run, {"a": tmp / "a"}, tmp / f"{placements[0][0]}.json", tmp / "comp",
            env=tmp / "env.exr", cfg=cfg, progress=False)
    return tmp


def test_compose_cache_recomputes_only_what_a_moved_object_touches(tmp_path, caplog, capsys):
    from comgs_dr.stages.compose import ComposeConfig, compose
    from comgs_dr.train.run import write_run_info
    data = _nerf_folder(tmp_path / "data")
    run = tmp_path / "scene_run"
    write_run_info(run, data, "scene", 1, False)
    save_ply(plane(n=30), str(run / "point_cloud.ply"))
    objs = {}
    for k, alb in (("a", (0.8, 0.2, 0.2)), ("b", (0.2, 0.2, 0.8))):
        p = ball((0, 0, 0), 0.3, alb, n=600)
        d = tmp_path / k
        d.mkdir()
        save_ply(p, str(d / "point_cloud.ply"))
        _probes_for(p, count=60).save(d / "probes.npz")
        objs[k] = d
    em.write_exr(tmp_path / "env.exr", sun_map(32), "octahedral")
    place = {"a": Similarity(1.0, np.eye(3), np.array([-0.4, 0, 0.3])),
             "b": Similarity(1.0, np.eye(3), np.array([0.4, 0, 0.3]))}
    write_placements(tmp_path / "t.json", place)
    cfg = ComposeConfig(shadow=occ.ShadowConfig(count=150, res=8, supersample=1),
                        scene_views=4, min_consistent=1)
    out = tmp_path / "comp"
    s1 = compose(run, objs, tmp_path / "t.json", out, env=tmp_path / "env.exr", cfg=cfg,
                 progress=False)
    assert len(s1["pairs"]["traced"]) + len(s1["pairs"]["culled"]) == 6
    assert (out / "shadow_probes.npz").is_file() and (out / "probes" / "b.npz").is_file()
    assert set(json.loads((out / "edit.json").read_text())["timings"]) >= {
        "lighting", "probe_placement", "occlusion_tracing", "total"}
    place["b"] = Similarity(1.0, euler_xyz_deg(0, 0, 30), np.array([0.5, 0.2, 0.3]))
    write_placements(tmp_path / "t.json", place)
    s2 = compose(run, objs, tmp_path / "t.json", out, env=tmp_path / "env.exr", cfg=cfg,
                 progress=False)
    redone = set(s2["pairs"]["traced"]) | set(s2["pairs"]["culled"])
    assert redone == {"occ_region_a__b", "occ_region_b__a", "occ_region_b__b",
                      "occ_own_a__b", "occ_own_b__a"}
    assert s2["pairs"]["reused"] == ["occ_region_a__a"]
    assert "scene_surface" not in s2["recomputed"] and "own_a" not in s2["recomputed"]
    # the folder renders: from its XML in any Mitsuba pipeline, and through render-comp
    xml = mi.load_file(str(out / "composition.xml"))
    assert np.isfinite(np.asarray(mi.render(xml, spp=16))).all()
    # ... from a copy of the folder too: the XML names the folder's files relative to itself
    import shutil
    copy = shutil.copytree(out, tmp_path / "moved")
    assert str(out) not in (copy / "composition.xml").read_text()
    (copy / "probes" / "b.npz").unlink()           # a file missing: a clear error at load
    with pytest.raises(Exception) as ei:
        mi.load_file(str(copy / "composition.xml"))
    assert "the 'probes_b' file 'probes/b.npz' is not found" in error_chain_text(ei.value)
    from comgs_dr.cli import main
    capsys.readouterr()
    assert main(["render-comp", str(copy), "--cameras", str(tmp_path / "data" / "transforms_test.json"),
                 "--res", "8", "--quiet"]) == 2                  # exit 2, not a traceback
    assert "the composition's probes_b file is missing" in capsys.readouterr().err
    shutil.copy(out / "probes" / "b.npz", copy / "probes" / "b.npz")
    np.testing.assert_array_equal(np.asarray(mi.render(mi.load_file(str(copy / "composition.xml")), spp=16, seed=1)),
                                  np.asarray(mi.render(xml, spp=16, seed=1)))
    from comgs_dr.stages.render_comp import render_comp
    gt = tmp_path / "gt"
    gt.mkdir()
    for i in range(4):
        Image.fromarray(np.full((24, 24, 3), 100, np.uint8)).save(gt / f"r_{i}.png")
    m = render_comp(out, tmp_path / "data" / "transforms_test.json", "sop", gt, rays=16,
                    progress=False)
    assert m["frames"] == 4 and len(m["per_frame"]) == 4 and np.isfinite(m["psnr"])
    assert (out / "renders" / "sop" / "r_3.png").is_file()
    assert json.loads((out / "metrics_sop.json").read_text())["ssim"] == m["ssim"]
    first = [np.asarray(Image.open(out / "renders" / "sop" / f"r_{i}.png")) for i in range(4)]
    # the dataset folder itself: its test views, loaded as step 1 loads them (same frames)
    (out / "renders" / "sop" / "old_frame.png").write_bytes(b"")     # an earlier run's frame
    with caplog.at_level("WARNING", logger="comgs_dr.stages.render_comp"):
        m2 = render_comp(out, tmp_path / "data", "sop", rays=16, progress=False)
    assert "1 frame(s) not of these cameras (e.g. old_frame.png)" in caplog.text
    assert "metrics_sop.json is from an earlier run" in caplog.text
    assert m2["frames"] == 4 and m2["resolution"] == [24, 24] and m2["cameras"] == str(tmp_path / "data")
    assert (out / "renders" / "sop" / "r_3.png").is_file()
    # the same cameras (to 2e-16) and the same pixels: a reloaded scene renders the same
    # (surfel_shapes sorts the shapes; before, 1 load in ~6 changed 7 % of a frame's pixels)
    from comgs_dr.data.comp_folder import camera_source
    for c1, c2 in zip(camera_source(tmp_path / "data" / "transforms_test.json", np.eye(4)),
                      camera_source(tmp_path / "data", np.eye(4))):
        assert c1["name"] == c2["name"]
        np.testing.assert_allclose(c1["to_world"], c2["to_world"], atol=1e-9)
    for i in range(4):
        np.testing.assert_array_equal(
            np.asarray(Image.open(out / "renders" / "sop" / f"r_{i}.png")), first[i])
    with pytest.raises(FileNotFoundError, match="dataset folder not found"):
        render_comp(out, tmp_path / "nowhere", "sop", progress=False)
    with pytest.raises(ValueError, match="no such object"):
        render_comp(out, tmp_path / "data" / "transforms_test.json", "sop", gt,
                    {"zebra": "albedo=1,0,0"}, progress=False)
    cams_json = tmp_path / "data" / "transforms_test.json"
    with pytest.raises(ValueError, match="do not apply to variant 'paste'"):
        render_comp(out, cams_json, "paste", materials={"a": "albedo=1,0,0"}, progress=False)
    with pytest.raises(ValueError, match="res 16×16 is not the ground truth's size"):
        render_comp(out, cams_json, "sop", gt, res=16, progress=False)      # before any frame
    with pytest.raises(ValueError, match="beyond the 8192²"):
        render_comp(out, cams_json, "sop", res=(10000, 9000), progress=False)
    only = tmp_path / "camsonly"                    # a folder with just transforms_test.json
    only.mkdir()
    shutil.copy(cams_json, only / "transforms_test.json")
    assert render_comp(out, only, "noshadow", res=8, rays=4, progress=False)["frames"] == 4
    # the command line: an input error raised inside mi.render (probes that exist but are
    # not baked) exits 2 with its own message, not Dr.Jit's custom-op RuntimeError
    from comgs_dr.cli import main
    raw = tmp_path / "raw"
    shutil.copytree(out, raw)
    pa = ProbeSet.load(out / "probes" / "a.npz")
    ProbeSet(pa.positions, pa.normals, pa.res, pa.radius).save(raw / "probes" / "a.npz")
    capsys.readouterr()
    assert main(["render-comp", str(raw), "--cameras", str(cams_json), "--res", "8",
                 "--rays", "4", "--quiet"]) == 2
    assert "probes of 'a' are not baked" in capsys.readouterr().err
    assert main(["render-comp", str(out), "--cameras", str(cams_json), "--variant", "paste",
                 "--material", "a:albedo=1,0,0", "--quiet"]) == 2
    assert "material overrides do not apply to variant 'paste'" in capsys.readouterr().err
    # placement errors name the object
    (tmp_path / "bad.json").write_text(json.dumps({"a": {"transform": np.diag([1, 2, 1, 1.0]).ravel().tolist()},
                                                   "b": {"location": [0, 0, 0]}}))
    with pytest.raises(ValueError, match="'a'.*scale|scale.*'a'"):
        compose(run, objs, tmp_path / "bad.json", out, env=tmp_path / "env.exr", cfg=cfg,
                progress=False)
    assert (out / "composition.json").is_file()      # a folder that existed stays whole
    # a failing compose leaves no empty folder behind; a tiny scale is named as such
    with pytest.raises(FileNotFoundError):
        compose(run, objs, tmp_path / "nowhere.json", tmp_path / "fresh", env=tmp_path / "env.exr",
                cfg=cfg, progress=False)
    assert not (tmp_path / "fresh").exists()
    tiny = {"a": Similarity(1e-9, np.eye(3), np.zeros(3)), "b": place["b"]}
    with pytest.raises(ValueError, match="'a' placed at scale 1e-09 .* check its placement's scale"):
        compose(run, objs, tiny, tmp_path / "fresh", env=tmp_path / "env.exr", cfg=cfg,
                progress=False)
    assert not (tmp_path / "fresh").exists()
    write_placements(tmp_path / "one.json", {"a": place["a"]})
    with pytest.raises(ValueError, match="no placement for \\['b'\\]"):
        compose(run, objs, tmp_path / "one.json", out, env=tmp_path / "env.exr", cfg=cfg,
                progress=False)


def test_composition_shows_the_scene_runs_learned_sky(tmp_path):
    """A scene run with step 1's sky (background.exr): compose records it, and every
    variant draws it where nothing covers a pixel (decoded to linear); the covered pixels
    are unchanged."""
    from comgs_dr.core.cameras import camera_rays
    from comgs_dr.core.colorspace import srgb_decode
    from comgs_dr.stages.compose import ComposeConfig, compose
    from comgs_dr.stages.render_comp import load_comp_scene
    from comgs_dr.train import background as bgenv
    from comgs_dr.train.run import write_run_info
    data = _nerf_folder(tmp_path / "data")
    run = tmp_path / "scene_run"
    write_run_info(run, data, "scene", 1, False)
    save_ply(plane(n=30), str(run / "point_cloud.ply"))
    d = tmp_path / "obj"
    d.mkdir()
    p = ball((0, 0, 0), 0.3, (0.8, 0.2, 0.2), n=600)
    save_ply(p, str(d / "point_cloud.ply"))
    _probes_for(p, count=60).save(d / "probes.npz")
    em.write_exr(tmp_path / "env.exr", sun_map(32), "octahedral")
    write_placements(tmp_path / "t.json", {"obj": Similarity(1.0, np.eye(3), np.array([0, 0, 0.3]))})
    cfg = ComposeConfig(shadow=occ.ShadowConfig(count=100, res=8, supersample=1),
                        scene_views=4, min_consistent=1)
    out = tmp_path / "comp"
    compose(run, {"obj": d}, tmp_path / "t.json", out, env=tmp_path / "env.exr", cfg=cfg,
            progress=False)                                       # before the sky exists
    sensor = perspective([0.0, -4.0, 1.0], target=[0.0, 0.0, 0.8], res=16, fov=60)
    plain = np.array(mi.render(load_comp_scene(out, "paste", sensors=[sensor])))
    dirs = octa.texel_directions_np(16).reshape(16, 16, 3)
    sky = np.clip(0.5 + 0.4 * dirs[..., 2:3], 0, 1) * [0.6, 0.7, 0.9]      # display values
    bgenv.save(run, sky, np.ones((16, 16)))
    compose(run, {"obj": d}, tmp_path / "t.json", out, env=tmp_path / "env.exr", cfg=cfg,
            progress=False)
    assert json.loads((out / "composition.json").read_text())["scene"]["sky"].endswith(
        "background.exr")
    for variant in ("paste", "sop"):
        img = np.array(mi.render(load_comp_scene(out, variant, sensors=[sensor])))
        ref = plain if variant == "paste" else \
            np.array(mi.render(load_comp_scene(out, variant, sensors=[sensor], sky="")))
        empty = ref.sum(-1) == 0                                   # nothing covers these
        assert empty.sum() > 20
        sc = load_comp_scene(out, variant, sensors=[sensor])
        dirs_px, _ = camera_rays(sc.sensors()[0], 16, 16)
        up = np.asarray(dirs_px)[..., 2:3]
        expect = srgb_decode(np.clip(0.5 + 0.4 * up, 0, 1) * [0.6, 0.7, 0.9])
        assert np.allclose(img[empty], expect[empty], atol=0.03)
        full = ref.sum(-1) > 0
        assert np.abs(img[full] - ref[full]).max() < 0.6         # covered pixels barely move


def test_compose_warns_about_a_black_environment_map(tmp_path, caplog):
    """A black --env is accepted (a valid map) but said: the object keeps only its baked light."""
    import logging

    from comgs_dr.stages import compose as cs
    for value, warned in ((0.0, True), (0.5, False)):
        em.write_exr(tmp_path / "env.exr", np.full((8, 16, 3), value, np.float32), "equirect")
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="comgs_dr.stages.compose"):
            out = cs._lighting(["a"], {"a": np.zeros(3)}, tmp_path / "env.exr", None, 8,
                               tmp_path / "comp", {})
        assert out["paths"]["a"].is_file()
        assert ("is black" in caplog.text) == warned


def test_shadow_region_probes_say_when_fewer_than_asked(caplog):
    """Fewer facing scene points than probes asked: all are used, and the count is said."""
    import logging
    g = np.linspace(-1.0, 1.0, 10)
    pts = np.stack(np.meshgrid(g, g, [0.0]), -1).reshape(-1, 3)                 # 100 points
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    lo, hi = np.array([-0.2, -0.2, 0.1]), np.array([0.2, 0.2, 0.5])
    for count, short in ((5000, True), (20, False)):
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="comgs_dr.sops.occlusion"):
            ps = occ.shadow_region_probes(pts, nrm, lo, hi, occ.ShadowConfig(count=count, res=4))
        n = ps.meta["shadow_region"]["candidates"]
        assert ps.count == min(count, n) and 20 < n <= 100
        assert (f"{n} of the {count} asked" in caplog.text) == short


def _tilted_plane(tilt_deg=60.0, n=40, seed=0):
    """``plane()`` with each surfel turned by up to ``tilt_deg`` about a random horizontal
    axis: the normals scatter as a briefly trained scene's do, the surface stays flat."""
    d = plane(n).to_numpy()
    rng = np.random.default_rng(seed)
    ang = np.radians(rng.uniform(0.0, tilt_deg, len(d["means"])))
    phi = rng.uniform(0.0, 2 * np.pi, len(d["means"]))
    d["quats"] = np.stack([np.cos(ang / 2), np.sin(ang / 2) * np.cos(phi),
                           np.sin(ang / 2) * np.sin(phi), np.zeros_like(ang)], -1)
    return SurfelParams.from_numpy(**d)


def test_depth_normals_recover_a_flat_ground_from_scattered_surfel_normals():
    sc = scene_of({"scene": _tilted_plane()}, {"type": "surfel_gbuffer"})
    buf = group_gbuffer(sc, sc.sensors()[0], [0])
    ground = np.asarray(buf.weight[0]) > 0.99
    n_depth, valid = buf.depth_normals(0)
    tilt = lambda v: np.degrees(np.arccos(np.clip(np.asarray(v)[2], -1, 1)))   # noqa: E731
    surf, dep = tilt(buf.normal[0])[ground], tilt(n_depth)[ground]
    assert np.asarray(valid)[ground].mean() > 0.9
    assert np.median(surf) > 10.0                          # the surfels' own: scattered
    assert np.median(dep) < 0.4 * np.median(surf), (np.median(dep), np.median(surf))
    n0, _ = buf.depth_normals(0, radius=0)                 # unsmoothed: still flatter
    assert np.median(tilt(n0)[ground]) < np.median(surf)


def test_shadow_ratio_uses_the_depth_normals_by_default(sphere_over_plane):
    """On a flat ground whose surfels are tilted, a low sun blocked: S with the depth
    normals is close to S with the true (flat) normal at the same points; with the
    surfels' own it scatters. The integrator uses the depth normals unless told
    ``shadow_normals=surfel``."""
    low = np.array([0.85, -0.3, 0.43]) / np.linalg.norm([0.85, -0.3, 0.43])   # a 25° sun
    env = OctEnvmapBase.from_radiance(sun_map(64, direction=low))
    sc = scene_of({"scene": _tilted_plane(35.0)}, {"type": "surfel_gbuffer"})
    buf = group_gbuffer(sc, sc.sensors()[0], [0])
    pix = dr.compress(buf.weight[0] > 0.99)
    x, n_surf, _ = buf.points(0, pix)
    n_dep = dr.gather(mi.Vector3f, buf.depth_normals(0)[0], pix)
    flat = dr.zeros(mi.Vector3f, dr.width(pix)) + mi.Vector3f(0, 0, 1)
    blocker = ConeBlocker(low, 6.0)
    S = {k: np.asarray(shadow_ratio(x, v, env, blocker, rays=1024, seed=1))[0]
         for k, v in (("flat", flat), ("depth", n_dep), ("surfel", n_surf))}
    err_dep = np.abs(S["depth"] - S["flat"]).mean()
    err_surf = np.abs(S["surfel"] - S["flat"]).mean()
    assert err_dep < 0.5 * err_surf, (err_dep, err_surf)

    tmp, scene_p, b = sphere_over_plane
    shapes = {"scene": _tilted_plane(35.0), "ball": b}
    default, _ = _render(tmp, shapes, "trace")
    depth, _ = _render(tmp, shapes, "trace", shadow_normals="depth")
    surfel, _ = _render(tmp, shapes, "trace", shadow_normals="surfel")
    np.testing.assert_array_equal(default, depth)
    assert np.abs(surfel - depth).max() > 0.01
    with pytest.raises(Exception) as ei:
        _render(tmp, {"scene": scene_p, "ball": b}, "trace", shadow_normals="mesh")
    assert "shadow_normals must be probes, depth or surfel" in error_chain_text(ei.value)
    with pytest.raises(Exception) as ei:
        _render(tmp, {"scene": scene_p, "ball": b}, "trace", sun_rays=-1)
    assert "sun_rays must be ≥ 0" in error_chain_text(ei.value)
    with pytest.raises(Exception) as ei:
        _render(tmp, {"scene": scene_p, "ball": b}, "trace", sun_map_res=1)
    assert "sun_map_res must be 0 (trace) or ≥ 2" in error_chain_text(ei.value)


def test_plane_normals_flatten_scattered_points_and_keep_a_corner_apart():
    """Fused points on a flat ground with 1 % depth noise and normals scattered by up to
    40°: the plane fit is within 3° of up where the points' own normals are ~20° off on
    average; 0.1 from a wall the fit stays on the ground (reweighted), on the wall it turns."""
    rng = np.random.default_rng(0)
    g = rng.uniform(-1, 1, (6000, 2))
    ground = np.c_[g, 0.01 * rng.normal(size=len(g))]
    wall = np.c_[np.full(2000, 1.0) + 0.01 * rng.normal(size=2000),
                 rng.uniform(-1, 1, 2000), rng.uniform(0, 1, 2000)]
    pts = np.r_[ground, wall]
    tilt = np.radians(rng.uniform(0, 40, len(pts)))
    phi = rng.uniform(0, 2 * np.pi, len(pts))
    own = np.c_[np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.cos(tilt)]
    own[len(ground):] = own[len(ground):][:, [2, 1, 0]] * [-1, 1, 1]       # the wall faces −x
    at = np.array([[0.0, 0.0, 0.0], [0.5, 0.3, 0.0], [0.9, 0.0, 0.0], [1.0, 0.0, 0.5]])
    n = occ.plane_normals(pts, own, at, 0.2)
    ang = lambda v, w: np.degrees(np.arccos(np.clip(v @ w, -1, 1)))   # noqa: E731
    assert ang(own[:len(ground)], [0, 0, 1]).mean() > 15
    for i in range(3):
        assert ang(n[i], [0, 0, 1.0]) < 3.0, (i, n[i])
    assert ang(n[3], [-1.0, 0, 0]) < 5.0, n[3]
    lone = occ.plane_normals(pts, own, [[5.0, 5.0, 5.0]], 0.2)             # nothing in reach
    np.testing.assert_allclose(np.linalg.norm(lone), 1.0, atol=1e-9)


def test_receivers_take_the_shadow_probes_normals_by_default(sphere_over_plane, tmp_path):
    """The receivers' normals are the shadow probes' (KNN-blended) by default: probes whose
    normals lean 30° change the traced shadow, probes with the ground's true normal give
    the shadow of untilted surfels; a point with no probe in reach keeps its own normal."""
    from comgs_dr.integrators.comgs_composite import _probe_normals
    from comgs_dr.sops.query import ProbeGrid
    tmp, _, b = sphere_over_plane
    low = np.array([0.85, -0.3, 0.43]) / np.linalg.norm([0.85, -0.3, 0.43])
    em.write_exr(tmp_path / "low.exr", sun_map(64, direction=low), "octahedral")
    ps = _shadow_probes(plane(), {"ball": b})
    ps.save(tmp_path / "up.npz")
    lean = np.array([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))])
    ProbeSet(ps.positions, np.tile(lean, (ps.count, 1)), ps.res, ps.radius,
             texture=ps.texture).save(tmp_path / "lean.npz")
    kw = dict(env=str(tmp_path / "low.exr"), sun_rays=16)
    tilted = {"scene": _tilted_plane(35.0), "ball": b}
    up, _ = _render(tmp, tilted, "trace", shadow_probes=str(tmp_path / "up.npz"), **kw)
    up2, _ = _render(tmp, tilted, "trace", shadow_probes=str(tmp_path / "up.npz"),
                     shadow_normals="probes", **kw)
    leaned, _ = _render(tmp, tilted, "trace", shadow_probes=str(tmp_path / "lean.npz"), **kw)
    np.testing.assert_array_equal(up, up2)
    assert np.abs(leaned - up).max() > 0.01
    # the blend itself: probes' normals where one is in reach, the point's own elsewhere
    grid = (ProbeGrid(ps.positions, ps.radius), to_jit(mi.Vector3f, np.tile(lean, (ps.count, 1)).T))
    x = to_jit(mi.Point3f, np.array([[0.1, 0.2, 0.0], [50.0, 50.0, 0.0]]).T)
    own = to_jit(mi.Vector3f, np.array([[0.0, 0.6, 0.8], [0.0, 0.6, 0.8]]).T)
    n = np.asarray(_probe_normals(grid, x, own, 8)).T
    np.testing.assert_allclose(n[0], lean, atol=1e-5)
    np.testing.assert_allclose(n[1], [0.0, 0.6, 0.8], atol=1e-6)


def test_shadows_darken_the_sky_seen_through_a_translucent_ground(tmp_path):
    """Step 1 fits a ground pixel as its surfels plus T_final · sky; the shadow darkens that
    whole pixel: sop / noshadow is the same with the sky as without it (the sky showed
    through the shadow of a ground a few percent transparent, lightening it)."""
    from comgs_dr.stages.compose import ComposeConfig, compose
    from comgs_dr.stages.render_comp import load_comp_scene
    from comgs_dr.train import background as bgenv
    from comgs_dr.train.run import write_run_info
    data = _nerf_folder(tmp_path / "data")
    run = tmp_path / "scene_run"
    write_run_info(run, data, "scene", 1, False)
    g = plane(n=30).to_numpy()
    g["opacity_logit"][:] = 0.0                               # each surfel half transparent
    save_ply(SurfelParams.from_numpy(**g), str(run / "point_cloud.ply"))
    d = tmp_path / "obj"
    d.mkdir()
    p = ball((0, 0, 0), 0.3, (0.8, 0.2, 0.2), n=600)
    save_ply(p, str(d / "point_cloud.ply"))
    _probes_for(p, count=60).save(d / "probes.npz")
    low = np.array([0.85, -0.3, 0.43]) / np.linalg.norm([0.85, -0.3, 0.43])   # a long shadow
    em.write_exr(tmp_path / "env.exr", sun_map(32, direction=low), "octahedral")
    write_placements(tmp_path / "t.json", {"obj": Similarity(1.0, np.eye(3), np.array([0, 0, 0.3]))})
    bgenv.save(run, np.full((16, 16, 3), 0.9), np.ones((16, 16)))          # a bright sky
    cfg = ComposeConfig(shadow=occ.ShadowConfig(count=100, res=8, supersample=1),
                        scene_views=4, min_consistent=1)
    out = tmp_path / "comp"
    compose(run, {"obj": d}, tmp_path / "t.json", out, env=tmp_path / "env.exr", cfg=cfg,
            progress=False)
    sensor = perspective([-2.0, -3.0, 3.0], target=[-0.5, 0.0, 0.0], res=32, fov=60)
    ratio = {}
    for sky in (None, ""):
        extra = {} if sky is None else {"sky": sky}
        r = {v: np.array(mi.render(load_comp_scene(out, v, sensors=[sensor], **extra),
                                   seed=1))[..., :3].mean(-1) for v in ("sop", "noshadow")}
        ratio[sky] = r["sop"] / np.maximum(r["noshadow"], 1e-6)
    ground = r["noshadow"] > 0.02                             # (the sky off: only the ground)
    shade = ground & (ratio[""] < 0.9)                        # the ball's shadow on the ground
    assert shade.sum() >= 5
    np.testing.assert_allclose(ratio[None][shade], ratio[""][shade], atol=0.02)
