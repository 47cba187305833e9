"""Fixed-radius KNN probe query (sops.query) against the numpy brute-force reference."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core.hostarray import to_jit
from comgs_dr.sops.query import (
    BACKFACE_FLOOR,
    EPS_REL,
    ProbeGrid,
    brute_force_query,
    interpolate,
    query,
)


def to_mi(pts, normals):
    pts = np.asarray(pts, np.float32).reshape(-1, 3)
    normals = np.asarray(normals, np.float32).reshape(-1, 3)
    return to_jit(mi.Point3f, pts.T), to_jit(mi.Vector3f, normals.T)


def unit(v):
    v = np.asarray(v, np.float64)
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def run_both(probes, pts, normals, radius, k, **grid_kw):
    grid = ProbeGrid(probes, radius, **grid_kw)
    res = query(grid, *to_mi(pts, normals), k=k)
    ref = brute_force_query(probes, pts, normals, radius, k)
    return grid, res, ref


def assert_matches(res, ref, probes, pts, radius, k):
    """Same counts, fallbacks, neighbour sets (slot order free) and weights (1e-5).

    The query measures distances in float32, the reference in float64: a row may
    differ only through a probe whose distance is ambiguous at that precision (within
    1e-5·radius of the radius or of the k-th distance). With these data none are
    expected; at most 0.1 % of the rows are forgiven.
    """
    idx, w, cnt, fb = res.numpy()
    bidx, bw, bcnt, bfb = ref
    assert idx.shape == bidx.shape == (len(pts), k)
    np.testing.assert_array_equal(fb, bfb)
    assert res.n_fallback == int(bfb.sum())

    def canon(i, ww):   # rows sorted by probe id (an unused slot before a used one)
        keys = i * 4.0 + (ww > 0)          # used slot after an unused one of the same id
        srt = np.argsort(keys, axis=1, kind="stable")
        return np.take_along_axis(i, srt, 1), np.take_along_axis(ww, srt, 1)
    si, sw = canon(idx, w)
    bi, bwt = canon(bidx, bw)
    bad = np.flatnonzero((si != bi).any(1) | (cnt != bcnt))
    forgiven = 0
    for row in bad:
        d = np.linalg.norm(probes.astype(np.float64) - pts[row].astype(np.float64), axis=1)
        diff = np.setxor1d(idx[row][w[row] > 0], bidx[row][bw[row] > 0])
        kth = np.sort(d[d <= radius])[min(k, int(bcnt[row])) - 1] if bcnt[row] else radius
        amb = (np.abs(d[diff] - radius) < 1e-5 * radius) | (np.abs(d[diff] - kth) < 1e-5 * radius)
        assert amb.all(), f"row {row}: neighbours {idx[row]} vs brute force {bidx[row]}"
        forgiven += 1
    assert forgiven <= max(1, len(pts) // 1000)
    good = np.setdiff1d(np.arange(len(pts)), bad)
    np.testing.assert_allclose(sw[good], bwt[good], atol=1e-5, rtol=0)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-5)
    # unused slots: weight 0 and a valid (gather-safe) probe id
    assert (idx >= 0).all() and (idx < len(probes)).all()
    used = np.where(fb, 1, np.minimum(cnt, k))
    slot = np.arange(k)[None, :]
    assert (w[slot >= used[:, None]] == 0).all()
    assert (w[slot < used[:, None]] > 0).all()


# ---------------------------------------------------------------------------------------

@pytest.fixture
def random_scene(rng):
    probes = rng.uniform(0.0, 1.0, (2000, 3)).astype(np.float32)
    pts = rng.uniform(-0.1, 1.1, (5000, 3)).astype(np.float32)
    normals = unit(rng.normal(size=(5000, 3)))
    return probes, pts, normals


@pytest.mark.parametrize("radius", [0.06, 0.12])
def test_matches_brute_force(random_scene, radius):
    probes, pts, normals = random_scene
    grid = ProbeGrid(probes, radius)
    assert not grid.hashed and grid.table_size == np.prod(grid.dims)
    x, n = to_mi(pts, normals)
    for k in (1, 4, 8):
        res = query(grid, x, n, k=k)
        ref = brute_force_query(probes, pts, normals, radius, k)
        assert_matches(res, ref, probes, pts, radius, k)
        assert res.k == k and res.size == len(pts) and res.num_probes == len(probes)
        if radius == 0.12:
            assert (ref[2] > k).any()      # some points have more than k candidates


def test_count_is_uncapped_and_k_larger_than_probe_count(rng):
    probes = rng.uniform(0, 0.1, (3, 3)).astype(np.float32)
    pts = rng.uniform(0, 0.1, (50, 3)).astype(np.float32)
    normals = unit(rng.normal(size=(50, 3)))
    grid, res, ref = run_both(probes, pts, normals, 1.0, 8)
    assert_matches(res, ref, probes, pts, 1.0, 8)
    assert (res.numpy()[2] == 3).all()


def test_clustered_and_empty_neighbourhoods(rng):
    k, radius = 8, 0.1
    centres = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.5]], np.float32)
    probes = np.concatenate([c + rng.normal(0, 0.02, (60, 3)) for c in centres]
                            ).astype(np.float32)
    near = np.concatenate([c + rng.normal(0, 0.03, (300, 3)) for c in centres])
    # far: ≥ 0.3 from every probe, inside and outside the grid's bounding box
    far = np.array([[0.5, 0.5, 0.2], [0.5, 0.0, 0.0], [3.0, -2.0, 7.0], [-40, 0, 0],
                    [0.5, 1.0, 0.5], [1e4, 1e4, -1e4]])
    pts = np.concatenate([near, far]).astype(np.float32)
    normals = unit(rng.normal(size=(len(pts), 3)))
    grid, res, ref = run_both(probes, pts, normals, radius, k)
    assert_matches(res, ref, probes, pts, radius, k)
    idx, w, cnt, fb = res.numpy()
    assert (cnt[:len(near)] > k).mean() > 0.5            # clusters: more than k in range
    assert not fb[:len(near)].any()
    nf = len(far)
    assert fb[-nf:].all() and res.n_fallback == nf and (cnt[-nf:] == 0).all()
    d = np.linalg.norm(probes[None].astype(np.float64) - pts[-nf:, None], axis=2)
    np.testing.assert_array_equal(idx[-nf:, 0], d.argmin(1))   # nearest probe overall
    np.testing.assert_array_equal(w[-nf:, 0], 1.0)
    np.testing.assert_array_equal(w[-nf:, 1:], 0.0)


def test_point_on_probe_and_backface_weight():
    radius, a = 0.2, 0.05
    n = np.array([0.0, 0.0, 1.0], np.float32)
    x = np.array([0.3, 0.4, 0.5], np.float32)
    t = np.array([1.0, 0.0, 0.0], np.float32)
    th = 0.6
    probes = np.stack([
        x,                                                 # exactly at the point
        x + a * n,                                         # straight in front
        x - a * n,                                         # straight behind
        x + a * (np.sin(th) * t + np.cos(th) * n),         # oblique pair, mirrored
        x + a * (np.sin(th) * t - np.cos(th) * n)]).astype(np.float32)
    grid = ProbeGrid(probes, radius)
    res = query(grid, *to_mi(x[None], n[None]), k=8)
    idx, w, cnt, fb = res.numpy()
    assert np.isfinite(w).all() and cnt[0] == 5 and not fb[0]
    np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-6)
    wk = dict(zip(idx[0][w[0] > 0].tolist(), w[0][w[0] > 0].astype(np.float64)))
    assert idx[0, 0] == 0 and wk[0] == w.max()             # nearest first, dominant
    eps = EPS_REL * radius
    front, back = 0.5 * 2 + BACKFACE_FLOOR, BACKFACE_FLOOR
    np.testing.assert_allclose(wk[2] / wk[1], back / front, rtol=1e-4)
    c = np.cos(th)
    np.testing.assert_allclose(wk[4] / wk[3], (0.5 * (1 - c) + BACKFACE_FLOOR)
                               / (0.5 * (1 + c) + BACKFACE_FLOOR), rtol=1e-4)
    on = (1 / eps) * (0.5 + BACKFACE_FLOOR)                # d = 0: cos term vanishes
    np.testing.assert_allclose(wk[1] / wk[0], (front / a) / on, rtol=1e-4)


def test_invalid_inputs_raise(rng):
    probes = rng.uniform(0, 1, (20, 3)).astype(np.float32)
    grid = ProbeGrid(probes, 0.3)
    pts = rng.uniform(0, 1, (10, 3)).astype(np.float32)
    normals = unit(rng.normal(size=(10, 3)))
    pts[3, 1] = np.nan
    pts[7, 0] = np.inf
    with pytest.raises(ValueError, match=r"2 of 10 points are not finite"):
        query(grid, *to_mi(pts, normals))
    normals[2] = np.nan
    with pytest.raises(ValueError, match=r"1 of 10 normals are not finite"):
        query(grid, *to_mi(np.nan_to_num(pts), normals))
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="radius must be finite and > 0"):
            ProbeGrid(probes, bad)
    with pytest.raises(ValueError, match="no probes"):
        ProbeGrid(np.zeros((0, 3), np.float32), 0.1)
    with pytest.raises(ValueError, match=r"positions must be \[P, 3\]"):
        ProbeGrid(np.zeros((5, 2), np.float32), 0.1)
    with pytest.raises(ValueError, match="k must be an integer"):
        query(grid, *to_mi(np.nan_to_num(pts), unit(np.ones((10, 3)))), k=0)
    with pytest.raises(ValueError, match="no probes"):
        brute_force_query(np.zeros((0, 3)), pts, normals, 0.1, 4)


def test_gradient_through_interpolate(rng):
    P, N, k, radius = 300, 800, 8, 0.25
    probes = rng.uniform(0, 1, (P, 3)).astype(np.float32)
    pts = rng.uniform(0, 1, (N, 3)).astype(np.float32)
    normals = unit(rng.normal(size=(N, 3)))
    res = query(ProbeGrid(probes, radius), *to_mi(pts, normals), k=k)
    idx, w, _, _ = res.numpy()
    c = rng.normal(size=(N, 3)).astype(np.float32)          # d loss / d output
    vals_np = rng.normal(size=(P, 3)).astype(np.float32)

    # scalar per-probe values
    vals = to_jit(mi.Float, vals_np[:, 0])
    dr.enable_grad(vals)
    out = interpolate(res, vals)
    dr.backward(dr.sum(out * to_jit(mi.Float, c[:, 0])))
    np.testing.assert_allclose(np.asarray(out), (w * vals_np[idx, 0]).sum(1), atol=1e-5)
    want = np.zeros(P)
    np.add.at(want, idx.ravel(), (w * c[:, :1]).ravel())
    np.testing.assert_allclose(np.asarray(dr.grad(vals)), want, atol=1e-5)

    # colour per probe
    col = to_jit(mi.Color3f, vals_np.T)
    dr.enable_grad(col)
    out = interpolate(res, col)
    dr.backward(dr.sum(dr.dot(out, to_jit(mi.Color3f, c.T))))
    g = dr.grad(col)
    for ch in range(3):
        want = np.zeros(P)
        np.add.at(want, idx.ravel(), (w * c[:, ch:ch + 1]).ravel())
        np.testing.assert_allclose(np.asarray(g[ch]), want, atol=1e-5)
    with pytest.raises(ValueError, match="one entry per probe"):
        interpolate(res, to_jit(mi.Float, np.zeros(P + 1, np.float32)))


def test_hashed_grid_matches_brute_force(rng):
    # clusters spread over ±1000 with a 0.05 radius: ~4e4³ dense cells → hashed
    k, radius = 8, 0.05
    centres = rng.uniform(-1000, 1000, (12, 3))
    probes = np.concatenate([c + rng.uniform(-0.1, 0.1, (150, 3)) for c in centres]
                            ).astype(np.float32)
    pts = np.concatenate([c + rng.uniform(-0.13, 0.13, (250, 3)) for c in centres]
                         + [rng.uniform(-1000, 1000, (20, 3))]).astype(np.float32)
    normals = unit(rng.normal(size=(len(pts), 3)))
    grid, res, ref = run_both(probes, pts, normals, radius, k)
    assert grid.hashed and grid.dims == ()
    assert_matches(res, ref, probes, pts, radius, k)
    assert res.n_fallback >= 20 and (ref[2] > 0).mean() > 0.5
    # the same probe set hashed on purpose (unit-cube scene): same answer as dense
    probes2 = rng.uniform(0, 1, (1500, 3)).astype(np.float32)
    pts2 = rng.uniform(0, 1, (2000, 3)).astype(np.float32)
    n2 = unit(rng.normal(size=(2000, 3)))
    dense = query(ProbeGrid(probes2, 0.1), *to_mi(pts2, n2), k=4)
    hgrid = ProbeGrid(probes2, 0.1, max_dense_cells=0)
    hashed = query(hgrid, *to_mi(pts2, n2), k=4)
    assert hgrid.hashed
    for a, b in zip(dense.numpy(), hashed.numpy()):
        np.testing.assert_array_equal(a, b)
    assert_matches(hashed, brute_force_query(probes2, pts2, n2, 0.1, 4), probes2, pts2,
                   0.1, 4)
