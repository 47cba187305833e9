"""Adaptive density control on a toy case: counts, parameter/optimiser alignment."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.surfels import SurfelParams
from comgs_dr.surfels.params import field_names, field_to_numpy
from comgs_dr.train.density import DensityConfig, DensityController


def _toy():
    n = 6
    means = np.c_[np.arange(n, dtype=np.float32), np.zeros((n, 2))]
    ls = np.log(np.full((n, 2), 0.005))
    ls[1] = np.log([0.05, 0.02])          # large: split
    ls[3] = np.log([5.0, 5.0])            # huge: pruned
    op = np.full(n, 2.0)
    op[2] = -8.0                          # transparent: pruned
    sh = np.arange(n, dtype=np.float32)[:, None, None] * np.ones((n, 1, 3))
    return SurfelParams.from_numpy(means, np.tile([1, 0, 0, 0], (n, 1)), ls, op, sh)


def test_clone_split_prune_counts_and_alignment():
    p = _toy()
    ctl = DensityController(DensityConfig(grad_threshold=1e-3, percent_dense=0.01, max_fraction=1.0), p.count, extent=1.0)
    grads = np.zeros((6, 3))
    grads[0] = [1, 0, 0]                  # hot + small -> clone (lateral to the view)
    grads[1] = [0, 0, 1]                  # hot + large -> split
    grads[4] = [1e-6, 0, 0]               # cold
    ctl.accumulate(grads, field_to_numpy("means", p.means, 6), np.array([0.0, -10.0, 0.0]), 0.5)
    opt = mi.ad.Adam(lr=0.1)
    keys = {f: f for f in field_names()}
    for f in field_names():
        opt[f] = getattr(p, f)
    # give every surfel distinct moments: m = v = its index (per component)
    for f in field_names():
        value, promoted, lr, (t, m, v, vm) = opt.state[f]
        idx = np.arange(6, dtype=np.float32)
        a = np.broadcast_to(idx[:, None], field_to_numpy(f, m, 6).shape) if field_to_numpy(f, m, 6).ndim == 2 \
            else idx
        from comgs_dr.surfels.params import field_from_numpy
        opt.state[f] = (value, promoted, lr, (t, field_from_numpy(f, a, m), field_from_numpy(f, a + 100, m), vm))
    out, stats = ctl.densify_and_prune(p, opt, keys, rng=np.random.default_rng(0))
    assert stats == {"cloned": 1, "split": 1, "pruned": 2, "total": 6 - 1 - 2 + 1 + 2}
    q = out.to_numpy()
    # survivors in order: 0, 4, 5, clone of 0, two children of 1
    np.testing.assert_array_equal(q["sh"][:, 0, 0], [0, 4, 5, 0, 1, 1])
    # clone and source share the source's coverage: 1 − (1 − α')² = α
    a0 = 1 / (1 + np.exp(-2.0))
    a_pair = 1 / (1 + np.exp(-q["opacity_logit"][[0, 3]]))
    np.testing.assert_allclose(1 - (1 - a_pair) ** 2, a0, rtol=1e-5)
    np.testing.assert_allclose(q["opacity_logit"][[1, 2, 4, 5]], 2.0)    # others untouched
    children = q["means"][4:]
    assert np.all(np.abs(children[:, 0] - 1.0) < 0.3) and not np.allclose(children[0], children[1])
    np.testing.assert_allclose(q["log_scales"][4:], np.log(np.array([0.05, 0.02]) / 1.6)[None].repeat(2, 0),
                               rtol=1e-5)
    for f in field_names():
        assert np.array_equal(np.asarray(opt[f]), np.asarray(getattr(out, f))), f
        value, promoted, lr, (t, m, v, vm) = opt.state[f]
        mm = field_to_numpy(f, m, 6)
        mm = mm[:, 0] if mm.ndim == 2 else mm
        np.testing.assert_array_equal(mm, [0, 4, 5, 0, 0, 0], err_msg=f)   # new surfels: m = 0
        vv = field_to_numpy(f, v, 6)
        vv = vv[:, 0] if vv.ndim == 2 else vv
        np.testing.assert_array_equal(vv, [100, 104, 105, 100, 101, 101], err_msg=f)  # v: source's
        assert dr.width(v) == dr.width(getattr(out, f))
    # the optimiser still steps with the new sizes
    for f in field_names():
        dr.set_grad(opt[f], 1.0)
    opt.step()
    assert dr.width(opt["means"]) == 6


def test_opacity_reset_caps_and_zeroes_moments():
    p = _toy()
    ctl = DensityController(DensityConfig(), p.count, extent=1.0)
    opt = mi.ad.Adam(lr=0.1)
    opt["opacity_logit"] = p.opacity_logit
    dr.set_grad(opt["opacity_logit"], 1.0)
    opt.step()
    out = ctl.reset_opacity(p, opt, {"opacity_logit": "opacity_logit"})
    o = 1 / (1 + np.exp(-np.asarray(out.opacity_logit)))
    assert o.max() <= 0.01 + 1e-6 and o[2] < 0.001
    assert np.all(np.asarray(opt.state["opacity_logit"][3][1]) == 0)


def test_everything_pruned_is_an_error():
    p = _toy()
    d = p.to_numpy()
    d["opacity_logit"][:] = -20
    ctl = DensityController(DensityConfig(), 6, extent=1.0)
    with pytest.raises(RuntimeError, match="every surfel would be pruned"):
        ctl.densify_and_prune(SurfelParams.from_numpy(**d))
    with pytest.raises(ValueError, match="extent"):
        DensityController(DensityConfig(), 6, extent=0.0)


def test_growth_is_capped_by_fraction():
    rng = np.random.default_rng(0)
    n = 200
    p = SurfelParams.from_numpy(rng.normal(size=(n, 3)), np.tile([1, 0, 0, 0], (n, 1)),
                                np.log(np.full((n, 2), 0.001)), np.full(n, 2.0), np.zeros((n, 1, 3)))
    ctl = DensityController(DensityConfig(grad_threshold=1e-6, max_fraction=0.05), n, extent=1.0)
    ctl.accumulate(rng.normal(size=(n, 3)), field_to_numpy("means", p.means, n), np.array([0.0, 0, -10]), 0.5)
    g = ctl.grad_accum.copy()
    out, stats = ctl.densify_and_prune(p)
    assert stats["cloned"] == 10 and stats["total"] == 210
    # the clones are the surfels with the largest gradients
    top = np.sort(np.argsort(-g)[:10])
    np.testing.assert_allclose(np.sort(out.to_numpy()["means"][200:, 0]), np.sort(p.to_numpy()["means"][top, 0]))


def test_schedule_follows_the_run_progress():
    """``until`` stops densification and resets on the run's clock (iterations or time)."""
    ctl = DensityController(DensityConfig(start=100, stop=10 ** 6, interval=100, until=0.5,
                                          opacity_reset_interval=300), 6, extent=1.0)
    assert not ctl.due(50, 0.01) and ctl.due(100, 0.01) and not ctl.due(150, 0.01)
    assert ctl.due(1000, 0.5) and not ctl.due(1000, 0.51)        # past half of the budget
    assert ctl.reset_due(300, 0.2) and not ctl.reset_due(300, 0.6) and not ctl.reset_due(0, 0.0)


def test_run_fraction_uses_the_time_budget():
    """The trainer's clock: iterations done, or the time budget when it binds first."""
    import types

    from comgs_dr.stages.reconstruct import RadianceConfig, Trainer
    t = types.SimpleNamespace(cfg=RadianceConfig(iterations=1000), iteration=250, elapsed=90.0)
    assert Trainer.run_fraction(t) == 0.25
    t.cfg = RadianceConfig(iterations=1000, time_limit_s=100.0)
    assert Trainer.run_fraction(t) == 0.9
    t.elapsed = 500.0
    assert Trainer.run_fraction(t) == 1.0



def test_default_strategy_accumulates_then_edits_when_due():
    """The strategy object (train/strategy.py) accumulates after every backward pass and
    densifies / resets only on its schedule; a prune-only config never grows."""
    from comgs_dr.surfels.params import field_to_numpy as f2n
    from comgs_dr.train.strategy import DefaultStrategy, StepInfo
    p = _toy()
    cfg = DensityConfig(start=2, stop=4, interval=2, grad_threshold=1e-3, max_fraction=1.0,
                        opacity_reset_interval=3)
    st = DefaultStrategy(cfg, p.count, extent=1.0)
    assert st.grows
    grads = np.zeros((6, 3))
    grads[0] = [1, 0, 0]
    info = StepInfo(grad_means=grads, means=f2n("means", p.means, 6),
                    camera=np.array([0.0, -10.0, 0.0]), tan_half_fov=0.5)
    keys = {f: f for f in field_names()}
    rng = np.random.default_rng(0)
    st.step_post_backward(info)
    e1 = st.step_post_update(p, None, keys, 1, 0.1, rng)            # not due
    assert e1.params is None and e1.opacity_logit is None and e1.stats == {}
    st.step_post_backward(info)
    e2 = st.step_post_update(p, None, keys, 2, 0.2, rng)            # densify step
    assert e2.params is not None and e2.stats["densify_cloned"] == 1
    e3 = st.step_post_update(e2.params, None, keys, 3, 0.3, rng)    # reset step
    assert e3.params is None and e3.stats["opacity_reset"] == 1
    assert np.all(np.asarray(e3.opacity_logit) <= np.log(0.01 / 0.99) + 1e-5)
    prune_only = DefaultStrategy(DensityConfig(max_fraction=0.0), p.count, extent=1.0)
    assert not prune_only.grows
