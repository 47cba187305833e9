"""Octahedral environment map: conversions, Mitsuba orientation, exact sampling, gradients."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core import octahedral as octa
from comgs_dr.core.hostarray import to_jit
from comgs_dr.lighting import envmap as em


def _vec(a):
    a = np.asarray(a, np.float32)
    return to_jit(mi.Vector3f, a.T)


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _smooth_equirect(w=256):
    h = w // 2
    ex, ey = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    d = em.equirect_uv_to_dir_np(np.stack([ex.ravel(), ey.ravel()], -1))
    rgb = np.stack([1.5 + d[:, 0], 1 + 0.5 * d[:, 1], 1.2 + 0.8 * d[:, 2] ** 3], -1)
    return rgb.reshape(h, w, 3)


def _sun_equirect(w=512, power=1e6):
    img = np.full((w // 2, w, 3), 0.2)
    img[40:42, 100:102] = power           # a 2x2-pixel sun
    return img


def _power(img):
    h, w = img.shape[:2]
    sin_t = np.sin((np.arange(h) + 0.5) / h * np.pi)[:, None, None]
    return (img * sin_t).sum((0, 1)) * (2 * np.pi / w) * (np.pi / h)


def test_equirect_uv_round_trip(rng):
    d = _unit(rng, 5000)
    assert np.abs(em.equirect_uv_to_dir_np(em.equirect_dir_to_uv_np(d)) - d).max() < 1e-9


def test_equirect_oct_equirect_round_trip_smooth():
    eq = _smooth_equirect(256)
    oct_img = em.equirect_to_oct_np(eq, 64)
    back = em.oct_to_equirect_np(oct_img, 256)
    assert np.abs(back - eq).max() < 0.03


def test_oct_conversion_preserves_sun_power():
    eq = _sun_equirect(512)
    oct_img = em.equirect_to_oct_np(eq, 64)
    p_oct = (oct_img.reshape(-1, 3) * octa.texel_solid_angles_np(64)[:, None]).sum(0)
    assert np.allclose(p_oct, _power(eq), rtol=0.02)


def test_matches_mitsuba_envmap_orientation(rng):
    """Our equirect convention is the one the dataset generator gives Mitsuba's emitter."""
    from comgs_dr.data.synthetic import ENVMAP_TO_WORLD
    eq = _smooth_equirect(128).astype(np.float32)
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(eq),
                            "to_world": mi.ScalarTransform4f(ENVMAP_TO_WORLD)})
    d = _unit(rng, 2000)
    d = d[np.abs(d[:, 2]) < 0.95]         # away from the poles' filtering differences
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = -_vec(d)
    ref = np.array(emitter.eval(si)).T
    ours = em.sample_equirect_np(eq.astype(np.float64), em.equirect_dir_to_uv_np(d))
    assert np.abs(ref - ours).max() < 0.03


def test_eval_matches_numpy_and_round_trip_file(tmp_path, rng):
    eq = _smooth_equirect(256)
    env = em.OctEnvmap.from_equirect(eq, res=32)
    d = _unit(rng, 3000)
    got = np.array(env.eval(_vec(d))).T
    assert np.abs(got - em.sample_equirect_np(eq, em.equirect_dir_to_uv_np(d))).max() < 0.05
    p = env.save(tmp_path / "env.exr")
    arr, layout = em.read_envmap_file(p)
    assert layout == "octahedral" and arr.shape == (32, 32, 3)
    env2 = em.OctEnvmap.from_file(p, res=32)
    assert np.allclose(env2.radiance_np(), env.radiance_np(), rtol=1e-5)
    p2 = env.save(tmp_path / "env_eq.exr", equirect_width=128)
    arr2, layout2 = em.read_envmap_file(p2)
    assert layout2 == "equirect" and arr2.shape == (64, 128, 3)


def test_bad_files_and_values(tmp_path):
    bad = np.ones((8, 16, 3), np.float32)
    bad[2, 3, 1] = np.nan
    mi.Bitmap(bad).write(str(tmp_path / "nan.exr"))
    with pytest.raises(ValueError, match="non-finite"):
        em.read_envmap_file(tmp_path / "nan.exr")
    mi.Bitmap(np.ones((8, 8, 3), np.float32)).write(str(tmp_path / "sq.exr"))
    with pytest.raises(ValueError, match="layout"):
        em.read_envmap_file(tmp_path / "sq.exr")
    with pytest.raises(FileNotFoundError):
        em.read_envmap_file(tmp_path / "missing.exr")
    # 8-bit photos hold display values: refused, not read as radiance 0-255
    ldr = np.full((8, 16, 3), 200, np.uint8)
    for name in ("photo.png", "photo.jpg"):
        mi.Bitmap(ldr).write(str(tmp_path / name))
        with pytest.raises(ValueError, match=r"integer \(UInt8\) image: it holds display values"):
            em.read_envmap_file(tmp_path / name)
    mi.Bitmap(np.full((8, 16, 3), 2.5, np.float32)).write(str(tmp_path / "float.pfm"))
    assert em.read_envmap_file(tmp_path / "float.pfm")[0].max() == 2.5    # float formats read
    # negatives: compression noise near black is clamped quietly (an info line); deeper
    # ones warn
    import warnings
    noisy = np.ones((8, 16, 3), np.float32)
    noisy[1, 1, 0] = -1e-3
    mi.Bitmap(noisy).write(str(tmp_path / "noisy.exr"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert em.read_envmap_file(tmp_path / "noisy.exr")[0].min() == 0.0
    noisy[1, 1, 0] = -0.5
    mi.Bitmap(noisy).write(str(tmp_path / "damaged.exr"))
    with pytest.warns(UserWarning, match="1 negative values .most negative -0.5. clamped to 0"):
        assert em.read_envmap_file(tmp_path / "damaged.exr")[0].min() == 0.0
    with pytest.raises(ValueError, match="non-negative"):
        em.OctEnvmap(-np.ones((4, 4, 3)))
    with pytest.raises(ValueError, match=r"\[R, R, 3\]"):
        em.OctEnvmap(np.ones((4, 5, 3)))


@pytest.mark.parametrize("kind", ["smooth", "sun"])
def test_sampler_chi2(kind):
    eq = _smooth_equirect(128) if kind == "smooth" else _sun_equirect(256, 50.0)
    env = em.OctEnvmap.from_equirect(eq, res=16)
    sampler = env.sampler()
    test = mi.chi2.ChiSquareTest(
        domain=mi.chi2.SphericalDomain(),
        sample_func=lambda s: sampler.sample(mi.Point2f(s)).direction,
        pdf_func=lambda v: sampler.pdf(mi.Vector3f(v)),
        sample_dim=2, sample_count=400_000, res=64, ires=8)
    assert test.run(), test.messages


def test_sampler_pdf_consistency_and_normalisation(rng):
    env = em.OctEnvmap.from_equirect(_sun_equirect(256, 1e6), res=32)
    sampler = env.sampler()
    u = rng.uniform(0, 1, (20000, 2)).astype(np.float32)
    s = sampler.sample(to_jit(mi.Point2f, u.T))
    pdf_s = np.array(s.pdf)
    pdf_e = np.array(sampler.pdf(s.direction))
    assert np.all(np.isfinite(pdf_s)) and np.all(pdf_s > 0)
    inner = (np.abs(u - np.round(u)) > 1e-3).all(1)       # skip texel-boundary samples
    assert np.allclose(pdf_s[inner], pdf_e[inner], rtol=1e-3)
    # ∫ pdf dω = 1, by uniform sphere sampling
    d = _unit(rng, 400000)
    integral = np.array(sampler.pdf(_vec(d))).mean() * 4 * np.pi
    assert abs(integral - 1) < 0.05
    # the 1e6 sun texel (dilated to its 3×3 neighbours, which bilinear lookups light)
    # holds almost all the probability, radiance stays finite
    assert np.sort(sampler.pmf_np)[-9:].sum() > 0.9
    assert np.all(np.isfinite(np.array(env.eval(s.direction))))


def test_importance_sampled_estimate_is_unbiased(rng):
    """E[L(ω)·cos/pdf] equals the cosine-weighted integral computed on a fine grid."""
    eq = _sun_equirect(256, 200.0)
    env = em.OctEnvmap.from_equirect(eq, res=32)
    sampler = env.sampler()
    n = mi.Vector3f(0.3, 0.2, 0.93)
    n = n / dr.norm(n)
    u = rng.uniform(0, 1, (200000, 2)).astype(np.float32)
    s = sampler.sample(to_jit(mi.Point2f, u.T))
    L = env.eval(s.direction)
    est = np.array(L * dr.maximum(dr.dot(s.direction, n), 0) / s.pdf).mean(1)
    # reference: sum over a fine uv grid of the bilinear map, weighted by the Jacobian
    g = 512
    c = (np.arange(g) + 0.5) / g
    uu, vv = np.meshgrid(c, c)
    uv = to_jit(mi.Point2f, np.stack([uu.ravel(), vv.ravel()]))
    d = octa.uv_to_dir(uv)
    ref = np.array(env.eval(d) * dr.maximum(dr.dot(d, n), 0) * octa.jacobian_uv(uv)).sum(1) / g ** 2
    assert np.allclose(est, ref, rtol=0.03)


def test_eval_gradient_matches_finite_differences(rng):
    env = em.OctEnvmap.from_equirect(_smooth_equirect(64), res=4)
    d = _vec(_unit(rng, 50))
    theta = mi.Float(env.theta)
    dr.enable_grad(theta)
    loss = dr.sum(dr.sum(env.eval(d, theta)))
    dr.backward(loss)
    g = np.array(dr.grad(theta))
    base = np.array(env.theta, np.float64)
    for i in np.argsort(-np.abs(g))[:5]:
        hi, lo = base.copy(), base.copy()
        hi[i] += 1e-2
        lo[i] -= 1e-2
        f = lambda x: float(dr.sum(dr.sum(env.eval(d, to_jit(mi.Float, x))))[0])
        fd = (f(hi) - f(lo)) / 2e-2
        assert abs(fd - g[i]) < 2e-3 + 2e-3 * abs(fd)


def test_refresh_clamps_and_restores_border():
    env = em.OctEnvmap.constant(8, 1.0)
    t = np.array(env.theta)
    t[:] = 100.0
    env.theta = to_jit(mi.Float, t)
    env.refresh()
    assert np.allclose(np.array(env.theta), em.LOG_RANGE[1])
    assert np.all(np.isfinite(env.radiance_np()))
