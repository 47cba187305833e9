"""``sop_pbr`` through ``mi.render``: finite-difference gradients for materials, an env
texel and a probe texel, forward mode, the geometry cache, RGBA output, the MIS estimator."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core.cameras import perspective
from comgs_dr.core.hostarray import to_jit
from comgs_dr.emitters.octenvmap import OctEnvmapBase
from comgs_dr.sops.bake import bake
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.surfels.shape import SurfelShapeBase


@pytest.fixture(scope="module")
def probe_file(tmp_path_factory):
    from test_pbr import _sphere_over_plane
    params = _sphere_over_plane(n=1500)
    g = np.linspace(-0.5, 0.5, 5)
    gx, gy = np.meshgrid(g, g)
    pos = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 0.02)]
    probes = ProbeSet(positions=pos, normals=np.tile([0, 0, 1.0], (len(pos), 1)), res=6,
                      radius=0.35)
    scene = mi.load_dict({"type": "scene", "obj": SurfelShapeBase.from_params(params, id="obj"),
                          "sensor": perspective((0.0, -2.2, 1.6), res=16),
                          "integrator": {"type": "surfel_gbuffer"}})
    bake(scene, probes, max_hits=16, progress=False)
    rng = np.random.default_rng(3)
    probes.texture[..., :3] += rng.uniform(0, 0.2, probes.texture[..., :3].shape)   # some L_in
    # O away from its clip at 0 and 1, where central differences would straddle the kink
    probes.texture[..., 3] = 0.1 + 0.8 * probes.texture[..., 3]
    return params, probes.save(tmp_path_factory.mktemp("sop") / "probes.npz")


def _scene(probe_file, sampling="cosine", rays=16, res=16, film=None, sun=False, target=(0, 0, 0),
           **integ):
    params, path = probe_file
    rng = np.random.default_rng(0)
    p = params.to_numpy()
    n = len(p["opacity_logit"])
    p.update(albedo=rng.uniform(0.2, 0.9, (n, 3)), roughness=rng.uniform(0.3, 0.9, n),
             metallic=rng.uniform(0.0, 0.6, n))
    from comgs_dr.surfels import SurfelParams
    rad = rng.uniform(0.3, 1.2, (32, 32, 3) if sun else (8, 8, 3))
    if sun:                        # one texel of 32² (≈ 0.01 sr) holding ~90 % of the power
        rad[9, 12] = 8000.0
    sensor = perspective((0.0, -2.2, 1.6), target, res=res)
    if film:
        sensor["film"] = {**sensor["film"], **film}
    return mi.load_dict({
        "type": "scene", "obj": SurfelShapeBase.from_params(SurfelParams.from_numpy(**p), id="obj"),
        "env": OctEnvmapBase.from_radiance(rad), "sensor": sensor,
        "integrator": {"type": "sop_pbr", "probes": str(path), "rays": rays, "sampling": sampling,
                       "probe_k": 4, **integ}})


def _grad_and_fd(scene, key, index, eps, seed_grad=7):
    """AD gradient (through mi.render) and central differences of L = Σ w·image at one
    scalar of parameter ``key``, with the differential pass's seed for the FD renders."""
    params = mi.traverse(scene)
    w = to_jit(mi.TensorXf, np.random.default_rng(1).uniform(0.5, 1.5, (16, 16, 3)).astype(np.float32))
    x0 = np.array(params[key], np.float32).copy()
    flat_shape = x0.shape
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, seed=1, seed_grad=seed_grad)
    dr.backward(dr.sum(w * img, axis=None))
    g = np.array(dr.grad(params[key])).ravel()
    dr.disable_grad(params[key])

    def loss_at(v):
        x = x0.ravel().copy()
        x[index] = v
        params[key] = _like(params[key], x.reshape(flat_shape))
        params.update()
        with dr.suspend_grad():
            val = float(np.sum(np.asarray(w, np.float64) * np.asarray(mi.render(scene, seed=seed_grad))))
        return val
    v0 = float(x0.ravel()[index])
    fd = (loss_at(v0 + eps) - loss_at(v0 - eps)) / (2 * eps)
    loss_at(v0)
    return g, fd


def _like(cur, arr):
    """``arr`` (as ``np.array(cur)`` gives it: [3, N] for Color3f) back into cur's type."""
    return to_jit(type(cur), arr)


@pytest.mark.parametrize("key,eps", [("obj.albedo", 1e-2), ("obj.roughness", 1e-2),
                                     ("obj.metallic", 1e-2), ("env.data", 2e-2),
                                     ("integrator.probe_data", 2e-2)])
def test_fd_gradients_through_mi_render(probe_file, key, eps):
    """Cosine sampling: the sample set does not depend on the parameters, so the estimator
    is smooth in them and its AD gradient must equal central differences."""
    scene = _scene(probe_file)
    params = mi.traverse(scene)
    dr.enable_grad(params[key])
    params.update()
    w = to_jit(mi.TensorXf, np.random.default_rng(1).uniform(0.5, 1.5, (16, 16, 3)).astype(np.float32))
    img = mi.render(scene, params, seed=1, seed_grad=7)
    dr.backward(dr.sum(w * img, axis=None))
    g = np.array(dr.grad(params[key])).ravel()
    dr.disable_grad(params[key])
    assert np.isfinite(g).all() and np.abs(g).max() > 0
    for index in np.argsort(-np.abs(g))[:2]:
        g_all, fd = _grad_and_fd(scene, key, int(index), eps)
        assert abs(g_all[index] - fd) <= 0.03 * abs(fd) + 1e-3 * np.abs(g).max(), (key, index, g_all[index], fd)


@pytest.mark.parametrize("pixel_format", ["rgb", "rgba"])
def test_forward_mode_matches_reverse_mode(probe_file, pixel_format):
    """Also with an RGBA film (``scenes/relightable_object.xml``'s): forward mode used to
    abort the process there (Dr.Jit "dirty variable", ``deferred.rgba_tensor``)."""
    scene = _scene(probe_file, film={"pixel_format": pixel_format})
    params = mi.traverse(scene)
    key = "obj.albedo"
    dr.enable_grad(params[key])
    params.update()
    n = dr.width(params[key])
    direction = np.random.default_rng(2).normal(size=(3, n)).astype(np.float32)
    dr.set_grad(params[key], to_jit(mi.Color3f, direction))
    img = mi.render(scene, params, seed=1, seed_grad=5)
    dr.forward_to(img)
    fwd = float(np.sum(np.asarray(dr.grad(img), np.float64)))
    dr.disable_grad(params[key])
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, seed=1, seed_grad=5)
    dr.backward(dr.sum(img, axis=None))
    rev = float(np.sum(np.asarray(dr.grad(params[key])).T * direction.T))
    assert abs(fwd - rev) <= 1e-3 * abs(rev) + 1e-4


def test_a_view_that_sees_nothing_has_zero_gradient(probe_file):
    """A camera looking away from the object: ``dr.backward`` gives zero gradients (as
    Mitsuba's own integrators do), not "does not depend on the input variable(s)"."""
    scene = _scene(probe_file, target=(0.0, -10.0, 1.6))
    params = mi.traverse(scene)
    dr.enable_grad(params["obj.albedo"])
    params.update()
    img = mi.render(scene, params, seed=1, seed_grad=2)
    dr.backward(dr.sum(img, axis=None))
    assert np.all(np.asarray(dr.grad(params["obj.albedo"])) == 0)
    # where the object is in view, a parameter sop_pbr does not differentiate (geometry)
    # still raises Dr.Jit's error instead of a silent zero
    scene = _scene(probe_file)
    params = mi.traverse(scene)
    dr.enable_grad(params["obj.means"])
    params.update()
    img = mi.render(scene, params, seed=1, seed_grad=2)
    with pytest.raises(Exception, match="does not depend on the input"):
        dr.backward(dr.sum(img, axis=None))


def test_geometry_cache_survives_material_updates_only(probe_file):
    scene = _scene(probe_file)
    integ = scene.integrator()
    mi.render(scene)
    geo = integ._pbr._geo
    first = next(iter(geo.values()))
    params = mi.traverse(scene)
    params["obj.albedo"] = mi.Color3f(0.3, 0.6, 0.9) * dr.ones(mi.Color3f, dr.width(params["obj.albedo"]))
    params.update()
    img_a = np.asarray(mi.render(scene))
    assert next(iter(integ._pbr._geo.values())) is first          # reused
    means = np.asarray(params["obj.means"]).T.copy()
    means[:, 0] += 0.2
    params["obj.means"] = to_jit(mi.Point3f, means.T)
    params.update()
    img_b = np.asarray(mi.render(scene))
    assert next(iter(integ._pbr._geo.values())) is not first      # re-traced
    assert np.abs(img_a - img_b).mean() > 1e-3


def test_rgba_film_and_background(probe_file):
    rgba = np.asarray(mi.render(_scene(probe_file, film={"pixel_format": "rgba"}, hide_emitters=True)))
    assert rgba.shape == (16, 16, 4)
    a = rgba[..., 3]
    assert a.min() >= 0 and a.max() <= 1 and 0.05 < a.mean() < 0.99
    shown = np.asarray(mi.render(_scene(probe_file)))
    hidden = rgba[..., :3]
    empty = a < 1e-3
    assert empty.any() and np.all(hidden[empty] == 0) and np.all(shown[empty] > 0.2)


def test_mis_is_unbiased_and_beats_uniform_on_a_sun(probe_file):
    """Same rays per point: MIS and uniform agree in expectation (mean over seeds) with a
    high-count reference, and MIS has a much lower per-image error under a sun."""
    ref = np.mean([np.asarray(mi.render(_scene(probe_file, "mis", rays=512, sun=True), seed=s))
                   for s in range(4)], 0)
    errs, means = {}, {}
    for sampling in ("mis", "uniform"):
        scene = _scene(probe_file, sampling, rays=32, sun=True)
        imgs = [np.asarray(mi.render(scene, seed=100 + s)) for s in range(8)]
        means[sampling] = np.mean(imgs, 0).mean()
        errs[sampling] = np.sqrt(np.mean([(i - ref) ** 2 for i in imgs]))
    assert abs(means["mis"] / ref.mean() - 1) < 0.03, (means, ref.mean())
    assert abs(means["uniform"] / ref.mean() - 1) < 0.2, (means, ref.mean())
    assert errs["mis"] < 0.5 * errs["uniform"], errs
