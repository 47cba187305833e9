"""The surfel_gbuffer integrator: hit buffer vs brute force, XML loading, gradients."""
import mitsuba as mi
import numpy as np
import pytest
from conftest import error_chain_text, random_surfels
from ref_numpy import render_rays

from comgs_dr.core import cameras
from comgs_dr.core.hostarray import to_jit
from comgs_dr.integrators import surfel_gbuffer as gbuffer
from comgs_dr.surfels import composite as common
from comgs_dr.surfels import composite as compositing
from comgs_dr.surfels.scene import gbuffer_scene
from comgs_dr.surfels.shape import SurfelShapeBase


def _rays(rng, n):
    o = rng.uniform(-0.3, 0.3, (n, 3)) + np.array([0.0, -3.0, 0.0])
    tgt = rng.uniform(-0.5, 0.5, (n, 3))
    d = tgt - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


def _fast(params, o, d, K, targets=gbuffer.TARGETS):
    scene = gbuffer_scene(params, cameras.perspective([0, -3, 0], res=4))
    shapes = common.surfel_shapes(scene, "test")
    ray = mi.Ray3f(to_jit(mi.Point3f, o.T), to_jit(mi.Vector3f, d.T))
    hits, buf, acc, _ = compositing.trace_composite(scene, shapes, ray, K, 1e-6, targets)
    return hits, buf


class TestHitBufferVsBruteForce:
    @pytest.mark.parametrize("K", [4, 32])
    def test_same_ordered_hits_and_values(self, rng, K):
        params = random_surfels(rng, n=80, sh_degree=2)
        o, d = _rays(rng, 300)
        hits, buf = _fast(params, o, d, K)
        ref = render_rays(params.to_numpy(), o, d, K=K)
        ids = np.array(hits.ids).reshape(-1, K)
        cnt = np.array(hits.count)
        mism = [r for r in range(len(o)) if list(ids[r, :cnt[r]]) != ref["hits"][r]]
        # Ties within float32 precision at the ±3σ boundary or α = 1/255 may differ:
        # allow at most 1% of rays, and require that most rays hit something.
        assert len(mism) <= 0.01 * len(o), f"{len(mism)} rays with different hit lists"
        assert np.mean(cnt > 0) > 0.5
        good = np.setdiff1d(np.arange(len(o)), mism)
        for name, ch in [("color", 3), ("weight", 1), ("depth", 1), ("normal", 3), ("albedo", 3),
                         ("roughness", 1), ("metallic", 1)]:
            v = buf[name]
            a = np.array(v).reshape(ch, -1).T if ch == 3 else np.array(v)[:, None]
            np.testing.assert_allclose(a[good], ref[name][good], atol=2e-4, rtol=2e-4, err_msg=name)

    def test_unbiased_depth_is_depth_over_weight(self, rng):
        params = random_surfels(rng, n=40)
        o, d = _rays(rng, 200)
        _, buf = _fast(params, o, d, 16)
        W, D, Du = (np.array(buf[k]) for k in ("weight", "depth", "depth_unbiased"))
        m = W > 1e-3
        np.testing.assert_allclose(Du[m], D[m] / W[m], rtol=1e-5)
        assert np.all(Du[W <= 1e-6] == 0)

    def test_ray_missing_everything(self, rng):
        params = random_surfels(rng, n=10)
        o = np.array([[0.0, -3.0, 0.0]])
        d = np.array([[0.0, -1.0, 0.0]])                   # pointing away
        hits, buf = _fast(params, o, d, 8)
        assert int(hits.count[0]) == 0 and float(buf["weight"][0]) == 0.0


def test_only_requested_targets_are_produced(rng):
    params = random_surfels(rng, n=20)
    scene = gbuffer_scene(params, cameras.perspective([0, -3, 0], res=8), targets="weight,normal")
    integ = scene.integrator()
    assert integ.aov_names() == ["weight", "normal.X", "normal.Y", "normal.Z"]
    img = mi.render(scene)
    assert img.shape == (8, 8, 3 + 4)
    parts = integ.split(img)
    assert set(parts) == {"weight", "normal"}
    # Mitsuba re-raises constructor errors as RuntimeError with our message inside.
    with pytest.raises((ValueError, RuntimeError), match="'targets' has unknown entries"):
        gbuffer_scene(params, cameras.perspective([0, -3, 0], res=8), targets="colour")
    with pytest.raises((ValueError, RuntimeError), match="'max_hits' must be"):
        gbuffer_scene(params, cameras.perspective([0, -3, 0], res=8), max_hits=0)


def test_non_surfel_shape_is_refused(rng):
    params = random_surfels(rng, n=5)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "surfel_gbuffer"},
                          "s": SurfelShapeBase.from_params(params), "cube": {"type": "cube"},
                          "sensor": cameras.perspective([0, -3, 0], res=4)})
    with pytest.raises(Exception) as ei:
        mi.render(scene)
    assert "renders only 'surfels' shapes" in error_chain_text(ei.value)


def test_a_new_background_reuses_the_compiled_kernels(rng):
    """Step 1 draws a random background every step: changing it must not recompile the render
    (a literal grey level tripled the step time), and the colour must still follow it."""
    import drjit as dr
    scene = gbuffer_scene(random_surfels(rng, n=40), cameras.perspective([0, -3, 0], res=8),
                          targets="color,weight", background=0.25)
    integ = scene.integrator()
    import re

    def program(k):            # the kernel's code without its name and buffer alignments
        return re.sub(r"align \d+", "align", re.sub(r"drjit_[0-9a-f]+", "K", k["ir"].getvalue()))
    colours, known, new = {}, set(), []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for bg in (0.25, 0.5, 0.75):
            integ.background = bg
            dr.kernel_history()                              # clear
            parts = integ.split(mi.render(scene, spp=1))
            colours[bg] = (np.asarray(parts["color"]), np.asarray(parts["weight"]))
            jit = [k for k in dr.kernel_history() if "cache_hit" in k]   # compiled kernels
            assert jit
            progs = {program(k) for k in jit}
            if bg != 0.25:
                new.append(len(progs - known))
            known |= progs
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    # Dr.Jit may recompile a kernel whose buffers moved to another alignment; a new grey level
    # must not change any kernel's code (with a literal it changed the render kernel)
    assert new == [0, 0], new
    (c0, w), (c1, _) = colours[0.25], colours[0.5]
    w = w.reshape(c0.shape[:2] + (1,))
    assert 0.05 < w.mean() < 0.95                            # some pixels see the background
    # colour = Σ T α c + T_final · b, T_final = 1 − W: a step of 0.25 in b moves it by 0.25 (1 − W)
    np.testing.assert_allclose(c1 - c0, np.broadcast_to(0.25 * (1 - w), c0.shape), atol=2e-5)


def test_surfel_shapes_come_sorted_by_id(rng):
    """``mi.load_dict`` loads a scene's children in parallel, in no fixed order; the slots
    follow ``surfel_shapes``, which sorts by id, so a reloaded scene renders the same."""
    d = {"type": "scene"}
    for k in ("zeta", "alpha", "mid", "beta"):
        d[k] = SurfelShapeBase.from_params(random_surfels(rng, n=5), id=k)
    for _ in range(4):
        ids = [s.id() for s in common.surfel_shapes(mi.load_dict(d), "test")]
        assert ids == ["alpha", "beta", "mid", "zeta"]


def test_top_down_camera_and_non_finite_sensor():
    """``perspective`` looking along its up vector (a top-down view) gets another up, not a
    NaN matrix; a sensor whose to_world is not finite is a clear error in ``camera_rays``."""
    from comgs_dr.core.cameras import camera_rays
    s = cameras.perspective((0, 0, 3), (0, 0, 0), res=8)
    m = np.asarray(s["to_world"].matrix, np.float64)
    assert np.isfinite(m).all()
    np.testing.assert_allclose(m[:3, 2], [0, 0, -1], atol=1e-6)          # looks down
    np.testing.assert_allclose(m[:3, 1], [0, 1, 0], atol=1e-6)           # image up = +Y
    with pytest.raises(ValueError, match="up .* must be finite and non-zero"):
        cameras.perspective((0, -3, 0), up=(0, 0, 0))
    dirs, _ = camera_rays(s)
    assert np.isfinite(np.asarray(dirs)).all()
    bad = cameras.perspective((0, -3, 0), res=8)
    bad["to_world"] = mi.ScalarTransform4f(np.full((4, 4), np.nan).tolist())
    with pytest.raises(ValueError, match="to_world is not finite"):
        camera_rays(bad)
    with pytest.raises(ValueError, match="finite and distinct"):
        cameras.perspective((1, 2, 3), (1, 2, 3))
