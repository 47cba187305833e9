"""Deferred PBR: furnace, traced vs analytic occlusion, SOPs vs tracing, gradients, extremes."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core.hostarray import to_jit
from comgs_dr.lighting.envmap import OctEnvmap
from comgs_dr.shading.shade import ShadingConfig, ShadingPoints, shade
from comgs_dr.shading.visibility import NoVisibility, SopVisibility, TraceVisibility


def _v(a):
    a = np.asarray(a, np.float32)
    return to_jit(mi.Vector3f, a.T)


def _points(n, normal=(0, 0, 1), wo=None, albedo=0.8, rough=0.5, metal=0.0, pos=None):
    nn = np.tile(np.asarray(normal, float), (n, 1))
    nn /= np.linalg.norm(nn, axis=1, keepdims=True)
    w = nn if wo is None else np.tile(np.asarray(wo, float), (n, 1))
    w = w / np.linalg.norm(w, axis=1, keepdims=True)
    p = np.zeros((n, 3)) if pos is None else pos
    return ShadingPoints(position=mi.Point3f(_v(p)), normal=_v(nn), wo=_v(w),
                         albedo=mi.Color3f(dr.full(mi.Float, albedo, n)),
                         roughness=dr.full(mi.Float, rough, n),
                         metallic=dr.full(mi.Float, metal, n))


def _furnace_points(rng, n, rough):
    """n white dielectric points with random normals, viewed along the normal."""
    nn = rng.normal(size=(n, 3))
    nn /= np.linalg.norm(nn, axis=1, keepdims=True)
    return ShadingPoints(position=dr.zeros(mi.Point3f, n), normal=_v(nn), wo=_v(nn),
                         albedo=mi.Color3f(dr.full(mi.Float, 1.0, n)),
                         roughness=dr.full(mi.Float, rough, n), metallic=dr.zeros(mi.Float, n))


@pytest.mark.parametrize("sampling", ["uniform", "cosine"])
def test_white_furnace(rng, sampling):
    """A white Lambertian under a constant map L renders ≈ L (+ its small specular)."""
    pts = _furnace_points(rng, 500, 1.0)
    env = OctEnvmap.constant(16, 2.0)
    c = np.asarray(shade(pts, env, NoVisibility(), ShadingConfig(rays=256, sampling=sampling,
                                                                  indirect=False)))
    # diffuse 2.0 exactly (Hammersley + constant map); specular of F0=0.04 at roughness 1
    assert np.all(c >= 2.0 - 1e-3)
    assert np.all(c <= 2.0 * 1.06)


def test_white_furnace_mis_matches_in_expectation(rng):
    """MIS under a constant map: per-point noise, but the mean equals the exact cosine
    estimate (diffuse 2.0 + the small specular) within 1 %."""
    pts = _furnace_points(rng, 2000, 0.6)
    env = OctEnvmap.constant(16, 2.0)
    ref = np.asarray(shade(pts, env, NoVisibility(), ShadingConfig(rays=1024, sampling="cosine")))
    c = np.asarray(shade(pts, env, NoVisibility(), ShadingConfig(rays=64, sampling="mis")))
    assert np.isfinite(c).all()
    assert abs(c.mean() / ref.mean() - 1) < 0.01


@pytest.mark.parametrize("sampling", ["uniform", "mis"])
def test_extremes_are_finite(sampling):
    env = OctEnvmap.constant(16, 0.1)
    r = env.radiance_np()
    r[3, 5] = 1e6                           # a sun texel
    env = OctEnvmap(r)
    for rough, metal, wo in [(0.0, 1.0, (0, 0, 1)), (0.0, 0.0, (1, 0, 1e-6)),
                             (1.0, 1.0, (0, 1, 1e-7)), (0.0, 1.0, (1, 0, -0.2))]:
        pts = _points(64, wo=wo, rough=rough, metal=metal)
        c = np.asarray(shade(pts, env, NoVisibility(), ShadingConfig(rays=64, sampling=sampling)))
        assert np.all(np.isfinite(c)), (rough, metal, wo)
        assert np.all(c >= 0)


def _sphere_over_plane(n=6000, seed=0):
    import trimesh

    from comgs_dr.surfels.from_mesh import from_mesh
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    sphere.apply_translation([0, 0, 0.45])
    plane = trimesh.creation.box(extents=(2.0, 2.0, 0.02))
    plane.apply_translation([0, 0, -0.01])
    return from_mesh(trimesh.util.concatenate([sphere, plane]), n, seed=seed, opacity=0.99)


def _analytic_sphere_occlusion(x, d, c=(0, 0, 0.45), R=0.3):
    """1 where the ray x + t d (t > 0) hits the sphere."""
    oc = x - np.asarray(c)
    b = (oc * d).sum(1)
    disc = b * b - ((oc * oc).sum(1) - R * R)
    t = -b - np.sqrt(np.maximum(disc, 0))
    return ((disc > 0) & (t > 0)).astype(float)


@pytest.fixture(scope="module")
def sop_scene():
    """Sphere over a plane as surfels, and a 13×13 grid of probes just above the plane,
    baked by tracing (2×2 rays per texel)."""
    from comgs_dr.sops.bake import bake
    from comgs_dr.sops.probes import ProbeSet
    from comgs_dr.surfels.scene import gbuffer_scene
    params = _sphere_over_plane()
    scene = gbuffer_scene({"surfels": params}, [], targets="weight")
    g = np.linspace(-0.6, 0.6, 13)
    gx, gy = np.meshgrid(g, g)
    pos = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 0.02)]
    probes = ProbeSet(positions=pos, normals=np.tile([0, 0, 1.0], (len(pos), 1)), res=16,
                      radius=0.2)
    bake(scene, probes, max_hits=32, supersample=2, progress=False)
    return params, scene, probes


def test_traced_occlusion_matches_analytic(sop_scene, rng):
    from comgs_dr.surfels.trace import trace_visibility_np
    _, scene, _ = sop_scene
    m = 3000
    x = np.c_[rng.uniform(-0.3, 0.3, (m, 2)), np.full(m, 0.01)]
    d = rng.normal(size=(m, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    occ, rad = trace_visibility_np(scene, x, d, max_hits=32)
    ref = _analytic_sphere_occlusion(x, d)
    # surfel tiling of the sphere is a fuzzy boundary: compare away from silhouettes
    assert np.mean(np.abs(occ - ref)) < 0.06
    assert np.all(np.isfinite(rad)) and np.all(rad >= 0)


def test_sop_occlusion_close_to_traced(sop_scene, rng):
    """Probes on a grid above the plane, baked by tracing; their interpolated occlusion at
    plane points approximates the traced occlusion (paper: SOPs cache occlusion)."""
    from comgs_dr.sops.query import ProbeGrid
    from comgs_dr.surfels.trace import trace_visibility_np
    _, scene, probes = sop_scene
    pos = probes.positions
    m = 400
    x = np.c_[rng.uniform(-0.4, 0.4, (m, 2)), np.full(m, 0.01)]
    pts = _points(m, pos=x)
    vis = SopVisibility(probes.atlas(), ProbeGrid(probes.positions, probes.radius), 16, k=4)
    vis.prepare(pts)
    d = rng.normal(size=(m, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.05
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    occ, _ = vis.lookup(dr.arange(mi.UInt32, m), _v(d), False)
    traced, _ = trace_visibility_np(scene, x + [0, 0, 0.01], d, max_hits=32, radiance=False)
    err = np.abs(np.asarray(occ) - traced)
    # 16² texels ≈ 11° each and probes 0.1 apart: coarse per direction, unbiased on average
    assert err.mean() < 0.12
    assert abs(np.asarray(occ).mean() - traced.mean()) < 0.03


def test_shading_with_sops_and_trace_agree_on_average(sop_scene, rng):
    from comgs_dr.sops.query import ProbeGrid
    _, scene, probes = sop_scene
    pos = probes.positions
    m = 200
    x = np.c_[rng.uniform(-0.35, 0.35, (m, 2)), np.full(m, 0.0)]
    pts = _points(m, pos=x, rough=1.0)
    env = OctEnvmap.constant(16, 1.0)
    cfg = ShadingConfig(rays=128)
    c_sop = np.asarray(shade(pts, env, SopVisibility(probes.atlas(), ProbeGrid(pos, 0.2), 16),
                             cfg))
    c_tr = np.asarray(shade(pts, env, TraceVisibility(scene, 0.01, 32), cfg))
    c_none = np.asarray(shade(pts, env, NoVisibility(), cfg))
    assert np.all(np.isfinite(c_sop)) and np.all(np.isfinite(c_tr))
    # the sphere darkens the plane under it; both sources see it
    assert c_tr.mean() < 0.97 * c_none.mean()
    assert abs(c_sop.mean() - c_tr.mean()) < 0.05 * c_tr.mean()


def _fd_check(f, x, idx, eps, tol):
    """Central differences of scalar f at entries idx of the numpy vector x."""
    out = []
    for i in idx:
        hi, lo = x.copy(), x.copy()
        hi[i] += eps
        lo[i] -= eps
        out.append((f(hi) - f(lo)) / (2 * eps))
    return np.array(out)


def test_gradients_materials_env_and_atlas(rng):
    """AD vs central differences for albedo, roughness, metallic, env θ and probe atlas."""
    from comgs_dr.sops.probes import ProbeSet
    from comgs_dr.sops.query import ProbeGrid
    m = 16
    x = np.c_[rng.uniform(-0.1, 0.1, (m, 2)), np.zeros(m)]
    wo = np.array([0.3, 0.2, 1.0])
    env = OctEnvmap(rng.uniform(0.2, 2.0, (4, 4, 3)))
    probes = ProbeSet(positions=[[0, 0, 0.05], [0.1, 0, 0.05]], normals=[[0, 0, 1]] * 2, res=4,
                      radius=0.5, texture=rng.uniform(0, 0.6, (2, 4, 4, 4)))
    grid = ProbeGrid(probes.positions, probes.radius)
    base = {"albedo": rng.uniform(0.2, 0.8, 3 * m), "roughness": rng.uniform(0.3, 0.9, m),
            "metallic": rng.uniform(0.1, 0.9, m),
            "env": np.asarray(env.theta, np.float64), "atlas": probes.bordered().ravel()
            .astype(np.float64)}
    wts = rng.uniform(0.5, 1.5, (3, m)).astype(np.float32)

    def loss(vals, grad=None):
        a = to_jit(mi.Float, vals["albedo"])
        r = to_jit(mi.Float, vals["roughness"])
        mt = to_jit(mi.Float, vals["metallic"])
        th = to_jit(mi.Float, vals["env"])
        at = to_jit(mi.Float, vals["atlas"])
        if grad is not None:
            dr.enable_grad(a, r, mt, th, at)
        pts = _points(m, wo=wo, pos=x)
        pts.albedo = dr.unravel(mi.Color3f, a)
        pts.roughness, pts.metallic = r, mt
        c = shade(pts, env, SopVisibility(at, grid, 4, k=2), ShadingConfig(rays=32), seed=3,
                  env_theta=th)
        val = dr.sum(dr.sum(c * to_jit(mi.Color3f, wts)))
        if grad is not None:
            dr.backward(val)
            grad.update(albedo=np.asarray(dr.grad(a)), roughness=np.asarray(dr.grad(r)),
                        metallic=np.asarray(dr.grad(mt)), env=np.asarray(dr.grad(th)),
                        atlas=np.asarray(dr.grad(at)))
        return float(np.asarray(val).ravel()[0])

    g = {}
    loss(base, g)
    for key, eps in [("albedo", 1e-2), ("roughness", 1e-2), ("metallic", 1e-2), ("env", 1e-2),
                     ("atlas", 1e-2)]:
        idx = np.argsort(-np.abs(g[key]))[:4]
        def f(v, key=key):
            return loss({**base, key: v})
        fd = _fd_check(f, base[key], idx, eps, None)
        ad = g[key][idx]
        assert np.all(np.abs(fd - ad) <= 0.03 * np.abs(fd) + 2e-3 * np.abs(ad).max()), \
            (key, fd, ad)


def test_roughness_at_the_shading_floor_keeps_its_gradient(rng):
    """Step 2 clamps roughness to ``min_roughness`` after each step; a point at the floor
    still gets the one-sided derivative upward (a ``dr.maximum`` floor gave it 0)."""
    env = OctEnvmap(rng.uniform(0.2, 2.0, (4, 4, 3)))
    cfg = ShadingConfig(rays=64, sampling="uniform", min_roughness=0.04)
    wts = to_jit(mi.Color3f, rng.uniform(0.5, 1.5, (3, 8)).astype(np.float32))

    def loss(r0, grad=False):
        pts = _points(8, wo=(0.3, 0.2, 1.0), metal=1.0, rough=r0)
        if grad:
            dr.enable_grad(pts.roughness)
        val = dr.sum(dr.sum(shade(pts, env, NoVisibility(), cfg, seed=3) * wts))
        if grad:
            dr.backward(val)
            return float(dr.sum(dr.grad(pts.roughness))[0])
        return float(np.asarray(val).ravel()[0])
    nan = _points(2, rough=float("nan"))
    assert np.isnan(np.asarray(shade(nan, env, NoVisibility(), cfg, seed=3))).all()  # not 0.04
    h = 1e-3
    fd = (loss(0.04 + h) - loss(0.04)) / h
    g = loss(0.04, grad=True)
    assert abs(fd) > 1e-2 and g == pytest.approx(fd, rel=0.05), (g, fd)


def test_cached_blend_matches_rendered_material_buffers(rng):
    """Fast path (cached hit weights + gathers) vs the reference mi.render G-buffer."""
    from conftest import random_surfels

    from comgs_dr.core.cameras import perspective
    from comgs_dr.shading.deferred import DeferredPbr
    from comgs_dr.surfels.scene import gbuffer_scene
    params = random_surfels(rng, n=300, extent=0.4, scale=(0.05, 0.15))
    scene = gbuffer_scene({"surfels": params}, [perspective((0.3, -2.0, 1.0), res=32)],
                          targets="weight")
    pbr = DeferredPbr(scene, OctEnvmap.constant(8, 1.0), NoVisibility(), ShadingConfig(rays=8),
                      max_hits=32, min_weight=0.05)
    pts, geo = pbr.shading_points(0)
    bufs = pbr.material_buffers(0)
    pix = geo["pix_np"]
    W = geo["W_np"].ravel()[pix, None]
    ref_a = np.asarray(bufs["albedo"]).reshape(-1, 3)[pix] / W
    ref_r = np.asarray(bufs["roughness"]).reshape(-1)[pix] / W[:, 0]
    assert len(pix) > 50
    assert np.allclose(np.asarray(pts.albedo).T, np.clip(ref_a, 0, 1), atol=2e-4)
    assert np.allclose(np.asarray(pts.roughness), np.clip(ref_r, 0, 1), atol=2e-4)
    # gradients reach per-surfel albedo through the blend
    alb = mi.Color3f(params.albedo)
    dr.enable_grad(alb)
    p2, _ = pbr.shading_points(0, {"albedo": alb, "roughness": params.roughness,
                                   "metallic": params.metallic})
    dr.backward(dr.sum(dr.sum(p2.albedo)))
    g = np.asarray(dr.grad(alb))
    assert np.isfinite(g).all() and g.sum() > 0


def test_sop_pbr_plugin_renders_from_files(tmp_path, rng):
    """The Mitsuba plugin: env map + probe files, sops / trace / none, clear errors."""
    from conftest import error_chain_text

    from comgs_dr.core.cameras import perspective
    from comgs_dr.sops.bake import bake
    from comgs_dr.sops.probes import ProbeSet
    from comgs_dr.surfels.shape import SurfelShapeBase
    params = _sphere_over_plane(n=3000)
    env_path = OctEnvmap(rng.uniform(0.2, 1.0, (8, 8, 3))).save(tmp_path / "env.exr")
    shape = SurfelShapeBase.from_params(params, id="obj")
    g = np.linspace(-0.5, 0.5, 6)
    gx, gy = np.meshgrid(g, g)
    pos = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 0.02)]
    probes = ProbeSet(positions=pos, normals=np.tile([0, 0, 1.0], (len(pos), 1)), res=8,
                      radius=0.3)
    base = {"type": "scene", "obj": shape,
            "sensor": perspective((0.0, -2.2, 1.6), res=24)}
    bake(mi.load_dict({**base, "integrator": {"type": "surfel_gbuffer"}}), probes,
         max_hits=16, progress=False)
    probe_path = probes.save(tmp_path / "probes.npz")
    imgs = {}
    for vis in ("sops", "trace", "none"):
        integ = {"type": "sop_pbr", "envmap": str(env_path), "envmap_res": 16, "rays": 16,
                 "visibility": vis}
        if vis == "sops":
            integ["probes"] = str(probe_path)
        scene = mi.load_dict({**base, "integrator": integ})
        img = np.asarray(mi.render(scene))
        assert img.shape == (24, 24, 3) and np.isfinite(img).all() and img.max() > 0
        imgs[vis] = img
    # occlusion darkens the plane under the sphere: both visibility sources see it
    assert imgs["sops"].mean() < imgs["none"].mean()
    assert imgs["trace"].mean() < imgs["none"].mean()
    with pytest.raises(Exception) as e:       # no map: neither a file nor an octenvmap emitter
        mi.render(mi.load_dict({**base, "integrator": {"type": "sop_pbr", "visibility": "none"}}))
    assert "octenvmap" in error_chain_text(e.value)
    with pytest.raises(Exception) as e:
        mi.load_dict({**base, "integrator": {"type": "sop_pbr", "envmap": str(env_path),
                                             "visibility": "sops"}})
    assert "probes" in error_chain_text(e.value)


def test_points_without_probe_neighbours_use_the_nearest_probe():
    """Empty probe neighbourhood: finite shading from the single nearest probe."""
    from comgs_dr.sops.probes import ProbeSet
    from comgs_dr.sops.query import ProbeGrid
    tex = np.zeros((2, 4, 4, 4))
    tex[0, ..., 3] = 1.0                 # probe 0: fully occluded
    probes = ProbeSet(positions=[[0, 0, 0], [5, 0, 0]], normals=[[0, 0, 1]] * 2, res=4,
                      radius=0.1, texture=tex)
    pts = _points(2, pos=np.array([[0.5, 0, 0], [4.0, 0, 0]]))    # both outside the radius
    vis = SopVisibility(probes.atlas(), ProbeGrid(probes.positions, probes.radius), 4)
    env = OctEnvmap.constant(8, 1.0)
    c = np.asarray(shade(pts, env, vis, ShadingConfig(rays=32, indirect=False)))
    assert np.isfinite(c).all()
    assert vis.knn.n_fallback == 2
    assert c[:, 0].max() < 1e-6 and c[:, 1].min() > 0.3      # nearest: probe 0 / probe 1
