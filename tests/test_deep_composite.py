"""Every surfel on a ray is composited: 200 overlapping surfels on one pixel.

With a fixed K-slot hit buffer (K = 24) the surfels behind the 24th were dropped and the
background added with the transmittance left: they got no gradient and the pixel showed
the background through them. ``surfel_gbuffer`` now walks the tile list again for rays
whose buffer is full while still open (``max_passes``). Checked against the NumPy
reference (no K limit), with colour, weight and gradients (central differences, and the
Python-unrolled compositing of the same hit list).
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from ref_numpy import render_rays

from comgs_dr.core import cameras
from comgs_dr.surfels import SurfelParams, composite
from comgs_dr.surfels.scene import gbuffer_scene

N, RES, K = 200, 4, 24


def _stack(opacity=0.06, seed=0, n=N):
    """n large, faint surfels facing a camera on −y, spread along y in [−0.5, 0.5]."""
    N = n
    rng = np.random.default_rng(seed)
    means = np.c_[rng.normal(0, 0.01, N), np.linspace(-0.5, 0.5, N), rng.normal(0, 0.01, N)]
    # w-first quaternion turning the local normal z onto the y axis
    q = np.tile([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0], (N, 1))
    return SurfelParams.from_numpy(
        means=means, quats=q, log_scales=np.full((N, 2), np.log(1.0)),
        opacity_logit=np.full(N, np.log(opacity / (1 - opacity))) + rng.normal(0, 0.1, N),
        sh=rng.uniform(-0.4, 0.4, (N, 1, 3)))


def _scene(params, passes):
    return gbuffer_scene(params, cameras.perspective([0, -3, 0], fov=10, res=RES),
                         max_hits=K, max_passes=passes, targets="color,weight", method="raster")


def _render(scene, params=None):
    img = mi.render(scene, params)
    return scene.integrator().split(img)


def _reference(params, scene):
    """The NumPy reference at the pixel centres' rays (no K limit)."""
    sensor = scene.sensors()[0]
    with dr.suspend_grad():
        xs = (np.arange(RES) + 0.5) / RES
        pos = np.stack(np.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)
        ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(pos[:, 0], pos[:, 1]), mi.Point2f(0.5))
    o = np.array(ray.o, np.float64).reshape(3, -1).T
    d = np.array(ray.d, np.float64).reshape(3, -1).T
    return render_rays(params.to_numpy(), o, d, K=100_000)


def test_two_hundred_surfels_on_a_pixel_match_the_reference():
    params = _stack()
    deep, shallow = _scene(params, 16), _scene(params, 1)
    ref = _reference(params, deep)
    n_ref = np.array([len(h) for h in ref["hits"]])
    assert n_ref.min() > 3 * K, n_ref          # the stack is far deeper than one buffer
    got = _render(deep)
    c = np.array(got["color"]).reshape(-1, 3)
    w = np.array(got["weight"]).reshape(-1)
    np.testing.assert_allclose(c, ref["color"], atol=2e-4, rtol=1e-3)
    np.testing.assert_allclose(w, ref["weight"][:, 0], atol=2e-4)
    assert deep.integrator().stopped_early == 0.0
    # one pass drops what lies behind the 24th hit: weight visibly short of the reference
    w1 = np.array(_render(shallow)["weight"]).reshape(-1)
    assert np.all(ref["weight"][:, 0] - w1 > 0.1)
    assert shallow.integrator().stopped_early == 1.0


def test_stopped_early_counts_rays_left_open():
    params = _stack(opacity=0.02)            # T after 2·24 hits ≈ 0.38: still open
    scene = _scene(params, 2)
    _render(scene)
    assert scene.integrator().stopped_early == 1.0


@pytest.mark.parametrize("which", [10, 60])
def test_gradient_of_a_surfel_behind_the_buffer(which):
    """∂(colour + weight)/∂(opacity logit) of surfel ``which`` (60: behind the 48th hit)
    by the adjoint pass = central differences. Opacity 0.04: all 200 hits are composited
    (T stays above T_MIN), so no hit-list cut makes the difference quotient jump."""
    params = _stack(opacity=0.04)
    scene = _scene(params, 16)
    mp = mi.traverse(scene)
    key = "surfels.opacity_logit"
    x0 = np.array(mp[key])

    def f(x):
        mp[key] = mi.Float(x)
        mp.update()
        out = _render(scene)
        return float((dr.sum(out["color"].array) + dr.sum(out["weight"].array))[0])

    h = 0.1                 # float32 sums: a larger step keeps rounding below 1 %
    xp, xm = x0.copy(), x0.copy()
    xp[which] += h
    xm[which] -= h
    fd = (f(xp) - f(xm)) / (2 * h)
    mp[key] = mi.Float(x0)
    mp.update()
    dr.enable_grad(mp[key])
    out = _render(scene, mp)
    dr.backward(dr.sum(out["color"].array) + dr.sum(out["weight"].array))
    g = np.array(dr.grad(mp[key]))[which]
    assert abs(fd) > 1e-3
    np.testing.assert_allclose(g, fd, rtol=2e-2)


def test_adjoint_equals_unrolled_reference_on_the_deep_list():
    """Reverse-mode gradients over a multi-pass hit list = plain AD through the
    Python-unrolled compositing of the same list (80 surfels: 4 passes of 24; the
    unrolled reference compiles one step per slot)."""
    from comgs_dr.surfels import raster
    params = _stack(n=80)
    scene = _scene(params, 16)
    shapes = composite.surfel_shapes(scene, "test")
    sensor = scene.sensors()[0]
    with dr.suspend_grad():
        xs = (np.arange(RES) + 0.5) / RES
        pos = np.stack(np.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)
        ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(pos[:, 0], pos[:, 1]), mi.Point2f(0.5))
        pix = mi.Vector2u(mi.UInt32(np.tile(np.arange(RES), RES)),
                          mi.UInt32(np.repeat(np.arange(RES), RES)))
    hits, still_open = raster.find_all_hits(shapes, sensor, ray, pix, K, max_passes=16)
    assert hits.K > 2 * K and not still_open.any() and np.array(hits.count).min() > 2 * K
    p = shapes[0].params
    targets = ("color", "weight")
    _, acc, T = composite.composite_hits(shapes, ray, hits, targets)
    dr.enable_grad(p.opacity_logit, p.sh)
    seed = {"color": mi.Color3f(0.3, -0.2, 0.5), "weight": mi.Float(0.7)}
    composite.composite_adjoint(dr.ADMode.Backward, shapes, ray, hits, acc, T, targets, seed)
    g_fast = (np.array(dr.grad(p.opacity_logit)), np.array(dr.grad(p.sh)))
    dr.set_grad(p.opacity_logit, 0)
    dr.set_grad(p.sh, 0)
    out = composite.composite_unrolled(shapes, ray, hits, targets)
    dr.backward(dr.sum(dr.sum(out["color"] * seed["color"]) + out["weight"] * seed["weight"]))
    g_ref = (np.array(dr.grad(p.opacity_logit)), np.array(dr.grad(p.sh)))
    for a, b in zip(g_fast, g_ref):
        np.testing.assert_allclose(a, b, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("passes", [0, 257])
def test_max_passes_out_of_range_is_refused(passes):
    from conftest import error_chain_text
    with pytest.raises(Exception) as e:
        _scene(_stack(n=4), passes)
    assert "'max_passes' must be in 1..256" in error_chain_text(e.value)
