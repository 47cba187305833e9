"""Gradients of the G-buffer targets w.r.t. every surfel parameter.

Three tiers:
1. the symbolic adjoint pass equals plain AD through the unrolled reference;
2. AD directional derivatives equal central differences with the hit buffer
   held fixed (so visibility jumps, ignored by design, cannot interfere);
3. end to end through ``mi.render``: reverse mode equals forward mode
   (<w, J v> = <Jᵀ w, v>) and matches central differences of the rendered image.
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import random_surfels

from comgs_dr.core import cameras
from comgs_dr.core.hostarray import to_jit
from comgs_dr.integrators import surfel_gbuffer as gbuffer
from comgs_dr.surfels import composite as common
from comgs_dr.surfels import composite as compositing
from comgs_dr.surfels.params import field_names
from comgs_dr.surfels.scene import gbuffer_scene

PARAMS = field_names()
TARGETS = gbuffer.TARGETS
K = 8
# Central-difference step per parameter (raw units) and the relative tolerance
# of FD vs AD. float32 rounding adds FD noise ≈ 1e-7·Σ|w·B|/h, allowed for with
# a floor of 1e-6·Σ|w·B|/h; rays near kinks are masked out below.
STEP = {"means": 1e-3, "quats": 1e-3, "log_scales": 3e-3, "opacity_logit": 1e-2, "sh": 1e-2,
        "albedo": 1e-2, "roughness": 1e-2, "metallic": 1e-2}
RTOL = 2e-2


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(7)
    params = random_surfels(rng, n=30, sh_degree=1, opacity=(-0.5, 2.5))
    scene = gbuffer_scene(params, cameras.perspective([0, -3, 0], res=4))
    shapes = common.surfel_shapes(scene, "test")
    o = rng.uniform(-0.2, 0.2, (256, 3)) + np.array([0.0, -3.0, 0.0])
    d = rng.uniform(-0.5, 0.5, (256, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ray = mi.Ray3f(to_jit(mi.Point3f, o.T), to_jit(mi.Vector3f, d.T))
    hits, out, acc, T = compositing.trace_composite(scene, shapes, ray, K, 1e-6, TARGETS)
    assert np.mean(np.array(hits.count) > 1) > 0.3        # enough overlap to test blending
    # Rays with a stored hit near the α ≥ 1/255 cut, the α ≤ 0.99 clamp or the
    # colour clamp max(c, 0), or at grazing incidence (|d·n| < 0.15, where α varies
    # too fast for a finite step), or with W < 0.1, get zero weight: there the fixed-hit objective
    # jumps (cut) or kinks (clamps) within ±h.
    smooth = np.ones(256, bool)
    rid = dr.arange(mi.UInt32, 256)
    for k in range(K):
        pos = rid * K + k
        smp, vals = compositing.surfel_values(shapes, dr.gather(mi.UInt32, hits.slots, pos),
                                              dr.gather(mi.UInt32, hits.ids, pos), ray,
                                              k < hits.count, ("color",))
        a, valid = np.array(smp.alpha), np.array(k < hits.count)
        c = np.array(vals["color"])
        cos = np.abs(np.array(dr.dot(smp.normal, ray.d)))
        smooth &= ~(valid & ((a < 3 * 1 / 255) | (a > 0.98) | np.any(c < 0.05, axis=0) | (cos < 0.15)))
    smooth &= np.array(acc["weight"]) > 0.1       # D/W is steep where W → 0
    assert smooth.mean() > 0.25
    weights = {t: rng.normal(size=(3 if t in ("color", "normal", "albedo") else 1, 256)) * smooth
               for t in TARGETS}
    return scene, shapes, ray, hits, acc, T, weights, rng


def _as(t, w):
    return to_jit(mi.Vector3f, w) if w.shape[0] == 3 else to_jit(mi.Float, w[0])


def _objective(out, weights, targets):
    L = mi.Float(0.0)
    for t in targets:
        v = out[t] * _as(t, weights[t])
        L += dr.sum(dr.sum(v) if dr.size_v(v) == 3 else v)
    return L


def _grad_adjoint(shapes, ray, hits, acc, T, weights, targets, name):
    p = getattr(shapes[0].params, name)
    dr.enable_grad(p)
    grads = {t: _as(t, weights[t]) for t in targets}
    compositing.composite_adjoint(dr.ADMode.Backward, shapes, ray, hits, acc, T, targets, grads)
    g = dr.grad(p)
    dr.disable_grad(p)
    return np.array(g).ravel(), p


def _grad_unrolled(shapes, ray, hits, weights, targets, name):
    p = getattr(shapes[0].params, name)
    dr.enable_grad(p)
    L = _objective(compositing.composite_unrolled(shapes, ray, hits, targets), weights, targets)
    dr.backward(L, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    g = dr.grad(p)
    dr.disable_grad(p)
    return np.array(g).ravel()


@pytest.mark.parametrize("target", TARGETS)
def test_adjoint_matches_unrolled_ad(setup, target):
    scene, shapes, ray, hits, acc, T, weights, _ = setup
    for name in PARAMS:
        ga, _ = _grad_adjoint(shapes, ray, hits, acc, T, weights, (target,), name)
        gu = _grad_unrolled(shapes, ray, hits, weights, (target,), name)
        scale = max(np.abs(gu).max(), 1e-6)
        np.testing.assert_allclose(ga, gu, atol=1e-4 * scale, rtol=1e-3, err_msg=f"{target}/{name}")


@pytest.mark.parametrize("target", TARGETS)
def test_ad_matches_central_differences(setup, target):
    scene, shapes, ray, hits, acc, T, weights, rng = setup
    checked = 0
    for name in PARAMS:
        g, p = _grad_adjoint(shapes, ray, hits, acc, T, weights, (target,), name)
        if not np.any(g):
            # Materials do not influence colour/geometry targets and vice versa.
            continue
        base = np.array(p)
        v = rng.normal(size=base.shape).astype(np.float32)
        h = STEP[name]

        def f(x):
            setattr(shapes[0].params, name, to_jit(type(p), x))      # hit buffer held fixed
            return float(_objective(compositing.composite_unrolled(shapes, ray, hits, (target,)),
                                    weights, (target,))[0])
        fd = (f(base + h * v) - f(base - h * v)) / (2 * h)
        setattr(shapes[0].params, name, to_jit(type(p), base))
        ad = float(np.dot(g, v.ravel()))
        out = compositing.composite_unrolled(shapes, ray, hits, (target,))
        l_abs = sum(float(np.abs(np.array(out[target]) * weights[t]).sum()) for t in (target,))
        noise = 1e-6 * l_abs / h
        assert abs(fd - ad) <= RTOL * max(abs(fd), abs(ad)) + noise, \
            f"{target}/{name}: fd={fd} ad={ad} noise floor={noise}"
        checked += 1
    assert checked >= 1


def _scalar(x) -> float:
    return float(np.asarray(x).ravel()[0])


def _render_setup(targets="all", res=12):
    rng = np.random.default_rng(3)
    params = random_surfels(rng, n=40, sh_degree=1)
    scene = gbuffer_scene(params, cameras.perspective([0, -3, 0.3], res=res, fov=35),
                                  max_hits=K, targets=targets)
    return scene, mi.traverse(scene), rng


def test_render_backward_equals_forward_mode():
    scene, params, rng = _render_setup()
    img0 = mi.render(scene)
    w = to_jit(mi.TensorXf, rng.normal(size=img0.shape).astype(np.float32))
    for name in ("surfels.means", "surfels.quats", "surfels.opacity_logit", "surfels.sh",
                 "surfels.albedo"):
        p = params[name]
        v = to_jit(type(p), rng.normal(size=np.array(p).shape).astype(np.float32))
        # reverse mode
        dr.enable_grad(p)
        params.update()
        img = mi.render(scene, params)
        dr.backward(dr.sum(img * w, axis=None))
        rev = float(np.dot(np.array(dr.grad(p)).ravel(), np.array(v).ravel()))
        dr.disable_grad(p)
        # forward mode
        dr.enable_grad(p)
        params.update()
        dr.set_grad(p, v)
        img = mi.render(scene, params)
        fwd = _scalar(dr.sum(dr.forward_to(img) * w, axis=None))
        dr.disable_grad(p)
        assert abs(rev - fwd) <= 1e-3 * max(abs(rev), abs(fwd)) + 1e-5, f"{name}: {rev} vs {fwd}"


def _layered_setup():
    """Four large, tilted, semi-transparent surfels whose ±3σ quads and α ≥ 1/255
    footprints cover the whole 12² view at every FD step: the rendered image is
    then smooth in every parameter and central differences are meaningful end to end."""
    from comgs_dr.surfels import SurfelParams
    rng = np.random.default_rng(5)
    n = 4
    tilt = rng.normal(0, 0.25, (n, 3))
    q = np.concatenate([np.ones((n, 1)), tilt], 1)           # near identity: normal ≈ +Z
    params = SurfelParams.from_numpy(
        means=np.c_[rng.uniform(-0.1, 0.1, (n, 2)), np.linspace(-0.3, 0.3, n)],
        quats=q, log_scales=np.log(rng.uniform(1.0, 1.5, (n, 2))),
        opacity_logit=rng.uniform(-1.0, 1.0, n), sh=rng.normal(0, 0.2, (n, 4, 3)),
        albedo=rng.uniform(0, 1, (n, 3)), roughness=rng.uniform(0, 1, n), metallic=rng.uniform(0, 1, n))
    scene = gbuffer_scene(params, cameras.perspective([0, 0, 3], up=[0, 1, 0], res=12, fov=20),
                                  max_hits=K)
    return scene, mi.traverse(scene), rng


@pytest.mark.parametrize("name,h", [("surfels.means", 1e-3), ("surfels.quats", 1e-3),
                                    ("surfels.log_scales", 1e-3), ("surfels.opacity_logit", 1e-3),
                                    ("surfels.sh", 1e-2), ("surfels.albedo", 1e-2),
                                    ("surfels.roughness", 1e-2), ("surfels.metallic", 1e-2)])
def test_render_gradient_matches_central_differences(name, h):
    """End to end through mi.render (BVH rebuilt at each FD step), all channels."""
    scene, params, rng = _layered_setup()
    img0 = mi.render(scene)
    assert float(np.array(scene.integrator().split(img0)["weight"]).min()) > 0.5  # view covered
    w = to_jit(mi.TensorXf, rng.normal(size=img0.shape).astype(np.float32))
    p = params[name]
    base = np.array(p)
    v = rng.normal(size=base.shape).astype(np.float32)
    dr.enable_grad(p)
    params.update()
    dr.backward(dr.sum(mi.render(scene, params) * w, axis=None))
    ad = float(np.dot(np.array(dr.grad(p)).ravel(), v.ravel()))
    dr.disable_grad(p)

    def f(x):
        params[name] = to_jit(type(p), x)
        params.update()
        return _scalar(dr.sum(mi.render(scene) * w, axis=None))
    fd = (f(base + h * v) - f(base - h * v)) / (2 * h)
    params[name] = to_jit(type(p), base)
    params.update()
    noise = 1e-6 * float(np.abs(np.array(img0) * np.array(w)).sum()) / h
    assert abs(fd - ad) <= RTOL * max(abs(fd), abs(ad)) + noise, f"fd={fd} ad={ad} noise={noise}"
