"""Octahedral mapping: round trips, Jacobian, bordered-atlas bilinear seams, gradients."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core import octahedral as octa
from comgs_dr.core.hostarray import to_jit


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _vec(a):
    a = np.asarray(a, np.float32)
    return to_jit(mi.Vector3f, a.T)


def test_round_trip_dir_uv_dir(rng):
    d = _unit(rng, 20000)
    d[:6] = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [1, 1, 0] / np.sqrt(2),
             [0.6, 0, -0.8]]
    uv = octa.dir_to_uv(_vec(d))
    back = np.array(octa.uv_to_dir(uv)).T
    assert np.abs(back - d).max() < 2e-6
    # NumPy twins agree with the Dr.Jit versions
    assert np.abs(octa.dir_to_uv_np(d) - np.array(uv).T).max() < 1e-6
    assert np.abs(octa.uv_to_dir_np(octa.dir_to_uv_np(d)) - d).max() < 1e-12


def test_round_trip_uv_dir_uv(rng):
    uv = rng.uniform(0, 1, (20000, 2))
    assert np.abs(octa.dir_to_uv_np(octa.uv_to_dir_np(uv)) - uv).max() < 1e-9


def test_jacobian_integrates_to_4pi_and_matches_finite_differences(rng):
    sa = octa.texel_solid_angles_np(32, sub=8)
    assert abs(sa.sum() - 4 * np.pi) < 1e-3
    # vertex/face-centre ratio of texel solid angles approaches 3√3
    assert 4.5 < sa.max() / sa.min() < 5.3
    # finite differences of the area of a small uv square mapped to the sphere
    uv = rng.uniform(0.02, 0.98, (200, 2))
    h = 1e-4
    def dirs(o):
        return octa.uv_to_dir_np(uv + o)
    a, b, c = dirs((0, 0)), dirs((h, 0)), dirs((0, h))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1) / h ** 2
    jac = np.array(octa.jacobian_uv(to_jit(mi.Point2f, uv.T)))
    # skip points within 2h of a fold line (|p.x|+|p.y| = 1 or p.x/p.y = 0)
    p = 2 * uv - 1
    ok = (np.abs(np.abs(p).sum(1) - 1) > 1e-3) & (np.abs(p).min(1) > 1e-3)
    assert np.allclose(area[ok], jac[ok], rtol=2e-3)


def test_border_source_matches_direction_continuity():
    """Each border texel copies the interior texel whose direction is closest to the
    direction of the border texel's (out-of-square) centre reflected back over the edge."""
    r = 8
    src = octa.border_source_index(r).reshape(r + 2, r + 2)
    dirs = octa.texel_directions_np(r)
    for yb in range(r + 2):
        for xb in range(r + 2):
            if 1 <= xb <= r and 1 <= yb <= r:
                assert src[yb, xb] == (yb - 1) * r + (xb - 1)
                continue
            # Border texel centre in uv, just outside [0,1]: its true direction is the one
            # of the mirrored point, which must be the copied texel's direction.
            u, v = (xb - 0.5) / r, (yb - 0.5) / r
            u2, v2 = u, v
            if v2 < 0 or v2 > 1:
                v2 = -v2 if v2 < 0 else 2 - v2
                u2 = 1 - u2
            if u2 < 0 or u2 > 1:
                u2 = -u2 if u2 < 0 else 2 - u2
                v2 = 1 - v2
            d = octa.uv_to_dir_np(np.array([[u2, v2]]))[0]
            assert np.allclose(dirs[src[yb, xb]], d, atol=1e-12), (xb, yb)


def _smooth(d):
    # smooth RGB + 1 function on the sphere
    return np.stack([1 + d[:, 0], 1 + 0.5 * d[:, 1] * d[:, 2], 2 + d[:, 2] ** 2,
                     0.5 + 0.3 * d[:, 0] * d[:, 1]], -1)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_bilinear_lookup_is_seamless(rng, channels):
    r = 16
    tiles = _smooth(octa.texel_directions_np(r))[:, :channels].reshape(1, r, r, channels)
    atlas = to_jit(mi.Float, octa.add_border_np(tiles).ravel())
    # directions concentrated near the seams: the equator's fold and the -Z vertex
    d = _unit(rng, 4000)
    d[:2000, 2] *= 0.02
    d[2000:3000, :2] *= 0.02
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    uv = octa.dir_to_uv(_vec(d))
    taps = octa.bilinear_taps(mi.UInt32(0), uv, r)
    got = np.array(octa.lookup(atlas, taps, channels))
    got = got.reshape(channels, -1).T if channels > 1 else got[:, None]
    err = np.abs(got - _smooth(d)[:, :channels])
    # bilinear error of a smooth function at 16² is a few 1e-2; without the wrap border
    # the seams would be off by O(1)
    assert err.max() < 0.08
    # and it is no worse at the seams than in the interior
    interior = _unit(rng, 2000)
    interior = interior[np.abs(interior[:, 2]) > 0.3]
    uv_i = octa.dir_to_uv(_vec(interior))
    gi = np.array(octa.lookup(atlas, octa.bilinear_taps(mi.UInt32(0), uv_i, r), channels))
    gi = gi.reshape(channels, -1).T if channels > 1 else gi[:, None]
    e_int = np.abs(gi - _smooth(interior)[:, :channels]).max()
    assert err.max() < 3 * e_int + 0.02


def test_lookup_reproduces_texel_centres_and_multi_tile(rng):
    r, p = 4, 3
    tiles = rng.uniform(0, 1, (p, r, r, 3))
    atlas = to_jit(mi.Float, octa.add_border_np(tiles).ravel())
    c = (np.arange(r) + 0.5) / r
    u, v = np.meshgrid(c, c)
    uv = to_jit(mi.Point2f, np.stack([np.tile(u.ravel(), p), np.tile(v.ravel(), p)]))
    tile = to_jit(mi.UInt32, np.repeat(np.arange(p), r * r))
    got = np.array(octa.lookup(atlas, octa.bilinear_taps(tile, uv, r), 3)).T
    assert np.allclose(got, tiles.reshape(-1, 3), atol=1e-6)
    near = np.array(octa.lookup_nearest(atlas, tile, uv, r, 3)).T
    assert np.allclose(near, tiles.reshape(-1, 3), atol=1e-6)


def test_border_refresher_matches_numpy(rng):
    r, p, ch = 6, 2, 4
    tiles = rng.uniform(0, 1, (p, r, r, ch))
    bordered = octa.add_border_np(tiles)
    scrambled = bordered.copy()
    scrambled[:, 0, :] = -5
    scrambled[:, :, -1] = 7
    ref = octa.BorderRefresher(p, r, ch)
    out = np.array(ref(to_jit(mi.Float, scrambled.ravel())))
    assert np.allclose(out, bordered.ravel(), atol=1e-7)
    with pytest.raises(ValueError, match="expected"):
        ref(to_jit(mi.Float, np.zeros(5, np.float32)))


def test_lookup_gradient_matches_finite_differences(rng):
    r = 4
    tiles = rng.uniform(0, 1, (1, r, r, 1))
    interior = to_jit(mi.Float, tiles.ravel())
    src = to_jit(mi.UInt32, octa.border_source_index(r))
    d = _unit(rng, 64)
    uv = octa.dir_to_uv(_vec(d))
    w = to_jit(mi.Float, rng.uniform(0.5, 1.5, 64).astype(np.float32))

    def loss(x):
        atlas = dr.gather(mi.Float, x, src)     # border built inside the graph here
        return dr.sum(w * octa.lookup(atlas, octa.bilinear_taps(mi.UInt32(0), uv, r), 1))

    dr.enable_grad(interior)
    val = loss(interior)
    dr.backward(val)
    g = np.array(dr.grad(interior))
    base = np.array(interior, np.float64)
    eps = 1e-2
    for i in rng.choice(r * r, 6, replace=False):
        hi, lo = base.copy(), base.copy()
        hi[i] += eps
        lo[i] -= eps
        fd = (float(loss(to_jit(mi.Float, hi))[0])
              - float(loss(to_jit(mi.Float, lo))[0])) / (2 * eps)
        assert abs(fd - g[i]) < 1e-3 + 1e-3 * abs(fd)


def test_bad_inputs():
    with pytest.raises(ValueError, match="square"):
        octa.add_border_np(np.zeros((1, 4, 5, 3)))
    with pytest.raises(ValueError, match="channels"):
        octa.lookup(mi.Float(0.0), octa.bilinear_taps(mi.UInt32(0), mi.Point2f(0.5, 0.5), 2), 2)
