"""``surfel_gbuffer`` with ``env_background``: the scene's environment emitter behind the
surfels (C + T_final · L_e(d)), differentiable w.r.t. the emitter and the surfels."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core import cameras
from comgs_dr.core.hostarray import to_jit
from comgs_dr.emitters.octenvmap import emitter_class
from comgs_dr.surfels import SurfelParams
from comgs_dr.surfels.scene import gbuffer_scene

RTOL = 2e-2


def _surfels(seed=5, n=4):
    """Large, tilted, semi-transparent surfels covering the 12² view (smooth in every
    parameter at FD steps, and T_final > 0 everywhere so the environment shows)."""
    rng = np.random.default_rng(seed)
    q = np.concatenate([np.ones((n, 1)), rng.normal(0, 0.25, (n, 3))], 1)
    return SurfelParams.from_numpy(
        means=np.c_[rng.uniform(-0.1, 0.1, (n, 2)), np.linspace(-0.3, 0.3, n)],
        quats=q, log_scales=np.log(rng.uniform(1.0, 1.5, (n, 2))),
        opacity_logit=rng.uniform(-1.5, 0.0, n), sh=rng.normal(0, 0.2, (n, 4, 3)),
        albedo=rng.uniform(0, 1, (n, 3)), roughness=rng.uniform(0, 1, n),
        metallic=rng.uniform(0, 1, n))


def _env(res=8, seed=1, value=None):
    rng = np.random.default_rng(seed)
    rad = np.full((res, res, 3), value) if value is not None else rng.uniform(0.2, 2.0, (res, res, 3))
    return emitter_class().from_radiance(rad)


def _scene(env, targets="color,weight", **kw):
    sensor = cameras.perspective([0, 0, 3], up=[0, 1, 0], res=12, fov=20)
    return gbuffer_scene(_surfels(), sensor, environment=env, max_hits=8, targets=targets,
                         env_background=True, **kw)


def _scalar(x):
    return float(np.asarray(x).ravel()[0])


def test_constant_environment_equals_grey_background():
    img_env = np.array(mi.render(_scene(_env(value=0.7))))
    sensor = cameras.perspective([0, 0, 3], up=[0, 1, 0], res=12, fov=20)
    grey = gbuffer_scene(_surfels(), sensor, max_hits=8, targets="color,weight", background=0.7)
    img_grey = np.array(mi.render(grey))
    assert np.abs(img_env - img_grey).max() < 1e-5
    weight = img_env[..., 3]
    assert 0.05 < weight.min() and weight.max() < 0.95        # the environment shows


def test_environment_ignored_unless_asked():
    sensor = cameras.perspective([0, 0, 3], up=[0, 1, 0], res=12, fov=20)
    plain = gbuffer_scene(_surfels(), sensor, environment=_env(), max_hits=8, targets="color,weight")
    none = gbuffer_scene(_surfels(), sensor, max_hits=8, targets="color,weight")
    assert np.abs(np.array(mi.render(plain)) - np.array(mi.render(none))).max() == 0


def test_mitsuba_envmap_works_as_background():
    """Any Mitsuba environment emitter: a ``constant`` one equals the grey background."""
    img = np.array(mi.render(_scene({"type": "constant", "radiance": {"type": "rgb",
                                                                      "value": 0.3}})))
    sensor = cameras.perspective([0, 0, 3], up=[0, 1, 0], res=12, fov=20)
    grey = gbuffer_scene(_surfels(), sensor, max_hits=8, targets="color,weight", background=0.3)
    assert np.abs(img - np.array(mi.render(grey))).max() < 1e-5


@pytest.mark.parametrize("name,h", [("environment.data", 1e-2), ("surfels.opacity_logit", 1e-3),
                                    ("surfels.means", 1e-3), ("surfels.sh", 1e-2)])
def test_render_gradient_matches_central_differences(name, h):
    scene = _scene(_env())
    params = mi.traverse(scene)
    rng = np.random.default_rng(7)
    img0 = mi.render(scene)
    w = to_jit(mi.TensorXf, rng.normal(size=img0.shape).astype(np.float32))
    p = params[name]
    base = np.array(p)
    v = rng.normal(size=base.shape).astype(np.float32)
    dr.enable_grad(p)
    params.update()
    dr.backward(dr.sum(mi.render(scene, params, seed=1, seed_grad=2) * w, axis=None))
    ad = float(np.dot(np.array(dr.grad(p)).ravel(), v.ravel()))
    dr.disable_grad(p)
    assert ad != 0.0

    def f(x):
        params[name] = to_jit(type(p), np.maximum(x, 0) if name == "environment.data" else x)
        params.update()
        return _scalar(dr.sum(mi.render(scene) * w, axis=None))
    fd = (f(base + h * v) - f(base - h * v)) / (2 * h)
    params[name] = to_jit(type(p), base)
    params.update()
    noise = 1e-6 * float(np.abs(np.array(img0) * np.array(w)).sum()) / h
    assert abs(fd - ad) <= RTOL * max(abs(fd), abs(ad)) + noise, f"fd={fd} ad={ad} noise={noise}"


def test_environment_backward_equals_forward_mode():
    scene = _scene(_env())
    params = mi.traverse(scene)
    rng = np.random.default_rng(8)
    img0 = mi.render(scene)
    w = to_jit(mi.TensorXf, rng.normal(size=img0.shape).astype(np.float32))
    p = params["environment.data"]
    v = to_jit(type(p), rng.normal(size=np.array(p).shape).astype(np.float32))
    dr.enable_grad(p)
    params.update()
    dr.backward(dr.sum(mi.render(scene, params, seed=1, seed_grad=2) * w, axis=None))
    rev = float(np.dot(np.array(dr.grad(p)).ravel(), np.array(v).ravel()))
    dr.disable_grad(p)
    dr.enable_grad(p)
    params.update()
    dr.set_grad(p, v)
    fwd = _scalar(dr.sum(dr.forward_to(mi.render(scene, params, seed=1, seed_grad=2)) * w,
                         axis=None))
    dr.disable_grad(p)
    assert abs(rev - fwd) <= 1e-3 * max(abs(rev), abs(fwd)) + 1e-5, f"{rev} vs {fwd}"
