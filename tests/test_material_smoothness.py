"""The edge-aware material smoothness of step 2 (train.material_smoothness): its graph, its
value and gradient against a numpy reference and central differences, and its effect in
a tiny step 2."""
import numpy as np
import pytest
from conftest import make_tiny_step1_run


def _two_patches(n=40, gap=0.0, seed=0):
    """Two interleaved point clouds on a plane, red and blue (a texture edge)."""
    rng = np.random.default_rng(seed)
    x = np.c_[rng.uniform(0, 1, (2 * n, 2)), np.zeros(2 * n)]
    x[n:, 0] += gap
    c = np.r_[np.tile([0.9, 0.1, 0.1], (n, 1)), np.tile([0.1, 0.1, 0.9], (n, 1))]
    return x, c, np.ones(2 * n)


def test_pairs_are_untied_across_a_colour_edge_and_far_away():
    from comgs_dr.train.material_smoothness import neighbour_pairs
    x, c, o = _two_patches()
    i, j, w = neighbour_pairs(x, c, o, k=6, sigma=0.1)
    same = (i < 40) == (j < 40)
    assert same.any() and w[same].min() > 0.99                  # same colour: full weight
    assert (~same).sum() == 0 or w[~same].max() < 1e-6           # red-blue pairs dropped
    i2, j2, w2 = neighbour_pairs(x, np.full_like(c, 0.5), o, k=6, sigma=0.1)
    assert ((i2 < 40) != (j2 < 40)).any()                        # one colour: tied across
    # a far cluster is not a neighbour (radius_factor × the median spacing)
    xf, cf, of = _two_patches(gap=100.0)
    i3, j3, _ = neighbour_pairs(xf, np.full_like(cf, 0.5), of, k=6)
    assert not ((i3 < 40) != (j3 < 40)).any()
    # transparent surfels weigh nothing
    o0 = o.copy()
    o0[:40] = 0.0
    i4, j4, _ = neighbour_pairs(x, c, o0, k=6)
    assert (i4 >= 40).all() and (j4 >= 40).all()


def test_pairs_reject_bad_input_and_handle_tiny_clouds():
    from comgs_dr.train.material_smoothness import neighbour_pairs
    x, c, o = _two_patches(n=5)
    with pytest.raises(ValueError, match="non-finite"):
        neighbour_pairs(np.where(np.arange(10)[:, None] == 3, np.nan, x), c, o)
    with pytest.raises(ValueError, match="expected"):
        neighbour_pairs(x[:, :2], c, o)
    with pytest.raises(ValueError, match="k >= 1"):
        neighbour_pairs(x, c, o, k=0)
    assert all(len(a) == 0 for a in neighbour_pairs(x[:1], c[:1], o[:1]))
    i, j, w = neighbour_pairs(x[:3], c[:3], o[:3], k=8)          # k capped at N − 1
    assert len(i) <= 6 and np.isfinite(w).all()


def _reference(a, r, m, i, j, w):
    per = np.abs(a[i] - a[j]).mean(1) + np.abs(r[i] - r[j]) + np.abs(m[i] - m[j])
    return float((w * per).sum() / w.sum())


def test_value_and_gradient_match_a_reference(variant):
    import drjit as dr
    import mitsuba as mi
    from comgs_dr.train.material_smoothness import material_smoothness, neighbour_pairs
    rng = np.random.default_rng(1)
    n = 60
    x, c, o = rng.normal(size=(n, 3)), rng.uniform(size=(n, 3)), rng.uniform(0.2, 1, n)
    i, j, w = neighbour_pairs(x, c, o, k=5, sigma=0.5)
    a, r, m = rng.uniform(size=(n, 3)), rng.uniform(size=n), rng.uniform(size=n)
    ji, jj, jw = mi.UInt32(i), mi.UInt32(j), mi.Float(w)

    def val(a_, r_, m_):
        return float(material_smoothness(mi.Color3f(a_.T), mi.Float(r_), mi.Float(m_),
                                         ji, jj, jw)[0])
    assert val(a, r, m) == pytest.approx(_reference(a, r, m, i, j, w), rel=1e-5)
    A, R, M = mi.Color3f(a.T), mi.Float(r), mi.Float(m)
    dr.enable_grad(A, R, M)
    dr.backward(material_smoothness(A, R, M, ji, jj, jw))
    ga, gr, gm = np.array(dr.grad(A)).T, np.array(dr.grad(R)), np.array(dr.grad(M))
    # exact gradient of the piecewise-linear loss: ± w / Σw per pair end
    ref_r = np.zeros(n)
    np.add.at(ref_r, i, w * np.sign(r[i] - r[j]))
    np.add.at(ref_r, j, -w * np.sign(r[i] - r[j]))
    assert np.allclose(gr, ref_r / w.sum(), atol=1e-6)
    # central differences of the float64 reference along random directions (h small enough
    # that no pair's difference changes sign: the loss is piecewise linear)
    h = 1e-6
    for g, k in ((ga, "a"), (gr, "r"), (gm, "m")):
        v = rng.normal(size=g.shape)
        arg = {"a": a, "r": r, "m": m}
        plus = {**arg, k: arg[k] + h * v}
        minus = {**arg, k: arg[k] - h * v}
        fd = (_reference(plus["a"], plus["r"], plus["m"], i, j, w)
              - _reference(minus["a"], minus["r"], minus["m"], i, j, w)) / (2 * h)
        assert float((g * v).sum()) == pytest.approx(fd, rel=1e-3, abs=1e-6)
    empty = mi.UInt32(np.zeros(0, np.uint32))
    assert float(material_smoothness(A, R, M, empty, empty, mi.Float(np.zeros(0)))[0]) == 0.0


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    return make_tiny_step1_run(tmp_path_factory.mktemp("smooth"))


def test_step2_with_the_prior_spreads_materials_less(tiny_run):
    """The same tiny step 2 with and without the prior: neighbours' materials differ less
    with it (the quantity it penalises, measured on the written point cloud)."""
    from comgs_dr.stages.decompose import MaterialConfig, train_material
    from comgs_dr.surfels import load_ply
    from comgs_dr.train.material_smoothness import pairs_from_params
    run, _ = tiny_run
    cfg = dict(iterations=40, rays=16, env_res=16, probe_count=150, probe_res=8,
               eval_every=40, eval_views=2, log_every=5, checkpoint_every=40)
    spread = {}
    for lam in (0.0, 1.0):
        out = run / f"mat_smooth_{lam}"
        s = train_material(run, out, MaterialConfig(**cfg, lambda_smooth=lam), progress=False)
        assert np.isfinite(s["psnr_test"])
        q = load_ply(str(out / "point_cloud.ply"))
        i, j, w = pairs_from_params(q)
        d = q.to_numpy()
        spread[lam] = _reference(d["albedo"], d["roughness"], d["metallic"], i, j, w)
    assert spread[1.0] < 0.8 * spread[0.0], spread
