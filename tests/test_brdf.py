"""Tests of comgs_dr.shading.brdf: samplers (chi-square), energy, reciprocity, AD
gradients vs finite differences, extremes, Hammersley sets, Monte Carlo consistency."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import comgs_dr  # noqa: F401  (sets up LLVM / plugins before mitsuba is used)
from comgs_dr.core.hostarray import to_jit
from comgs_dr.shading import brdf

N_MC = 1 << 18


# ---------------------------------------------------------------------------------------
# helpers (numpy in, Dr.Jit out)

def vec3(a):
    a = np.asarray(a, dtype=np.float32).reshape(-1, 3)                     # [N, 3]
    return to_jit(mi.Vector3f, a.T)


def col3(a, n):
    a = np.broadcast_to(np.asarray(a, dtype=np.float32), (n, 3))            # [N, 3]
    return to_jit(mi.Color3f, a.T)


def flt(a, n):
    return to_jit(mi.Float, np.broadcast_to(np.asarray(a, dtype=np.float32), (n,)))


def np3(v):
    return np.stack([np.asarray(v.x), np.asarray(v.y), np.asarray(v.z)], axis=1)  # [N, 3]


def dir_from_cos(cos_t, phi=0.0):
    s = float(np.sqrt(max(1.0 - cos_t * cos_t, 0.0)))
    return mi.Vector3f(s * float(np.cos(phi)), s * float(np.sin(phi)), float(cos_t))


def random_upper(rng, n_vec, min_cos=0.0):
    """[N, 3] unit vectors with n·w > min_cos for normals ``n_vec`` [N, 3]."""
    out = np.empty_like(n_vec)
    todo = np.ones(len(n_vec), bool)
    while todo.any():
        w = rng.normal(size=(todo.sum(), 3))
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        w *= np.sign(np.sum(w * n_vec[todo], 1))[:, None]
        ok = np.sum(w * n_vec[todo], 1) > min_cos
        idx = np.flatnonzero(todo)[ok]
        out[idx] = w[ok]
        todo[idx] = False
    return out


def unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)                     # [N, 3]


def point2(u):
    u = np.asarray(u, dtype=np.float32)                                     # [N, 2]
    return to_jit(mi.Point2f, u.T)


# ---------------------------------------------------------------------------------------
# 1. chi-square tests of the samplers

def _chi2(sample_func, pdf_func, **kw):
    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample_func,
                                 pdf_func=pdf_func, sample_dim=2, **kw)
    ok = test.run(significance_level=0.01, quiet=True)
    assert ok, test.messages


def test_chi2_uniform_hemisphere():
    _chi2(lambda u: brdf.sample_uniform_hemisphere(mi.Point2f(u))[0],
          brdf.pdf_uniform_hemisphere, sample_count=200_000)


def test_chi2_cosine_hemisphere():
    _chi2(lambda u: brdf.sample_cosine_hemisphere(mi.Point2f(u))[0],
          brdf.pdf_cosine_hemisphere, sample_count=200_000)


@pytest.mark.parametrize("alpha", [0.05, 0.3, 0.8])
@pytest.mark.parametrize("cos_o", [1.0, 0.6, 0.05])
def test_chi2_ggx_vndf(alpha, cos_o):
    wo = dir_from_cos(cos_o, phi=0.7)

    def sample(u):
        wi, pdf = brdf.sample_ggx_vndf(mi.Point2f(u), wo, alpha)
        # samples reflected below the horizon are invalid (pdf 0): weight 0
        return wi, dr.select(pdf > 0.0, 1.0, 0.0)

    # sharp lobes need a fine trapezoid rule for the reference pdf (ires=32, as Mitsuba's
    # own rough-dielectric tests do); ires=6 over-integrates the α=0.05 peak by ~8%
    _chi2(sample, lambda w: brdf.pdf_ggx_vndf(wo, w, alpha), sample_count=300_000,
          ires=32 if alpha < 0.1 else 6)


def test_pdfs_zero_below_horizon():
    w = vec3([[0.3, 0.1, -0.5], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    wo = dir_from_cos(0.7)
    for p in (brdf.pdf_uniform_hemisphere(w), brdf.pdf_cosine_hemisphere(w),
              brdf.pdf_ggx_vndf(wo, w, 0.3)):
        assert np.all(np.asarray(p) == 0.0)
    # wo below the surface: no valid VNDF sample
    _, pdf = brdf.sample_ggx_vndf(point2([[0.3, 0.6]]), mi.Vector3f(0.6, 0, -0.8), 0.3)
    assert np.asarray(pdf)[0] == 0.0


# ---------------------------------------------------------------------------------------
# Monte Carlo helpers (independent random numbers, float64 statistics)

def _estimate(sampler, r, m, cos_o, albedo=1.0, lobe="full", n=N_MC, seed=0):
    """Mean and standard error of f·cos/pdf (red channel), local frame n = +z."""
    u = point2(np.random.default_rng(seed).random((n, 2)))                  # [n, 2]
    wo = dir_from_cos(cos_o, phi=0.3)
    if sampler == "uniform":
        wi, pdf = brdf.sample_uniform_hemisphere(u)
    elif sampler == "cosine":
        wi, pdf = brdf.sample_cosine_hemisphere(u)
    else:
        wi, pdf = brdf.sample_ggx_vndf(u, wo, brdf.ggx_alpha(mi.Float(r)))
    d, s = brdf.eval_brdf_split(mi.Color3f(albedo), mi.Float(r), mi.Float(m),
                                mi.Vector3f(0, 0, 1), wo, wi)
    f = {"full": d + s, "diffuse": d, "specular": s}[lobe]
    w = dr.select(pdf > 0.0, f.x * dr.maximum(wi.z, 0.0) / pdf, 0.0)
    w = np.asarray(w, dtype=np.float64)                                     # [n]
    assert np.all(np.isfinite(w))
    return w.mean(), w.std() / np.sqrt(n)


# ---------------------------------------------------------------------------------------
# 2. energy (white furnace)

COMBOS = [(r, m, c) for r in (0.0, 0.05, 0.3, 0.7, 1.0) for m in (0.0, 0.5, 1.0)
          for c in (1e-3, 0.2, 0.6, 1.0)]


def test_specular_lobe_white_furnace_at_most_one():
    # VNDF estimator of the specular lobe: F·G2/G1(ω_o) ≤ 1 per sample when F ≤ 1.
    for r, m, c in COMBOS:
        mean, se = _estimate("vndf", r, m, c, lobe="specular", n=1 << 14)
        assert mean <= 1.0 + 1e-4, (r, m, c, mean)
    # metallic 1, smooth, near-normal: a perfect mirror loses (almost) no energy
    mean, _ = _estimate("vndf", 0.0, 1.0, 1.0, lobe="specular", n=1 << 14)
    assert mean == pytest.approx(1.0, abs=2e-3)


def test_diffuse_lobe_white_lambertian_is_one():
    for cos_o in (0.05, 0.5, 1.0):
        mean, se = _estimate("uniform", 0.5, 0.0, cos_o, lobe="diffuse")
        assert abs(mean - 1.0) < 5 * se + 1e-4, (cos_o, mean, se)
    mean, se = _estimate("uniform", 0.5, 0.4, 0.5, lobe="diffuse")
    assert abs(mean - 0.6) < 5 * se + 1e-4                       # (1 − m)


def test_full_brdf_albedo_bounds():
    # The simplified Disney model adds specular on top of a diffuse lobe of albedo 1−m
    # (no (1−F) weighting), so the white-furnace albedo is ≤ (1 − m) + 1 everywhere and
    # ≤ 1.05 at normal incidence (specular ≈ F0 = 0.04(1−m) + m, diffuse 1 − m).
    for r, m, c in COMBOS:
        sd, _ = _estimate("cosine", r, m, c, lobe="diffuse", n=1 << 12)
        ss, _ = _estimate("vndf", r, m, c, lobe="specular", n=1 << 14)
        assert sd + ss <= (1.0 - m) + 1.0 + 1e-4
        if c == 1.0:
            assert sd + ss <= 1.05, (r, m, sd + ss)
        if m == 1.0:
            assert sd + ss <= 1.0 + 1e-4


# ---------------------------------------------------------------------------------------
# 3. reciprocity

def test_reciprocity(rng):
    n = 4096
    nv = unit(rng, n)
    wo, wi = random_upper(rng, nv), random_upper(rng, nv)
    a = col3(rng.uniform(0, 1, (n, 3)), n)
    r = flt(np.concatenate([np.zeros(64), rng.uniform(0, 1, n - 64)]), n)
    m = flt(rng.uniform(0, 1, n), n)
    f1 = np3(brdf.eval_brdf(a, r, m, vec3(nv), vec3(wo), vec3(wi)))          # [N, 3]
    f2 = np3(brdf.eval_brdf(a, r, m, vec3(nv), vec3(wi), vec3(wo)))          # [N, 3]
    assert np.all(np.isfinite(f1)) and np.all(f1 >= 0)
    np.testing.assert_allclose(f1, f2, rtol=1e-5, atol=0)


# ---------------------------------------------------------------------------------------
# 4. gradients vs central finite differences

def test_gradients_match_finite_differences(rng):
    n, eps = 256, 1e-3
    nv = unit(rng, n)
    wo, wi = random_upper(rng, nv, 0.1), random_upper(rng, nv, 0.1)
    a0 = rng.uniform(0.05, 0.95, (n, 3))
    r0 = rng.uniform(0.2, 1.0, n)
    m0 = rng.uniform(0.05, 0.95, n)
    N_, WO, WI = vec3(nv), vec3(wo), vec3(wi)

    def f(a, r, m):
        return brdf.eval_brdf(col3(a, n), flt(r, n), flt(m, n), N_, WO, WI)

    for name in ("albedo", "roughness", "metallic"):
        a, r, m = col3(a0, n), flt(r0, n), flt(m0, n)
        var = {"albedo": a, "roughness": r, "metallic": m}[name]
        dr.enable_grad(var)
        out = brdf.eval_brdf(a, r, m, N_, WO, WI)
        dr.forward(var)                      # d/dvar along 1 (all channels for albedo)
        g = np3(dr.grad(out))                                               # [N, 3]
        step = {"albedo": (eps, 0, 0), "roughness": (0, eps, 0), "metallic": (0, 0, eps)}[name]
        fp = np3(f(a0 + step[0], r0 + step[1], m0 + step[2]))
        fm = np3(f(a0 - step[0], r0 - step[1], m0 - step[2]))
        fd = (fp - fm) / (2 * eps)                                          # [N, 3]
        scale = np.maximum(np.abs(np3(f(a0, r0, m0))), 1.0)
        assert np.all(np.isfinite(g)), name
        bad = np.abs(g - fd) > 2e-2 * np.abs(fd) + 2e-3 * scale
        assert not bad.any(), (name, g[bad][:5], fd[bad][:5])


def test_gradients_finite_at_extremes():
    nv = np.tile([[0.0, 0.0, 1.0]], (6, 1))
    wo = np.array([[np.sqrt(1 - 1e-12), 0, 1e-6], [0, 0, 1], [0.6, 0, 0.8],
                   [0.6, 0, 0.8], [0.6, 0, 0.8], [0, 0, 1]])
    wi = np.array([[-np.sqrt(1 - 1e-12), 0, 1e-6], [0, 0, 1], [-0.6, 0, 0.8],
                   [0.6, 0, -0.8], [1, 0, 0], [0, 0, -1]])
    a, r, m = col3(0.8, 6), flt([0, 0, 0, 0.5, 0.5, 1], 6), flt([1, 1, 0, 0.5, 0.5, 0], 6)
    dr.enable_grad(a, r, m)
    out = brdf.eval_brdf(a, r, m, vec3(nv), vec3(wo), vec3(wi))
    dr.backward(dr.sum(out.x + out.y + out.z))
    for v in (dr.grad(a).x, dr.grad(r), dr.grad(m)):
        assert np.all(np.isfinite(np.asarray(v)))
    # zero BRDF below the horizon → zero gradient there
    assert np.asarray(dr.grad(m))[3] == 0.0 and np.asarray(dr.grad(a).x)[5] == 0.0


# ---------------------------------------------------------------------------------------
# 5. extremes, frames, point sets

def test_extremes_finite_and_zero_below():
    nz = mi.Vector3f(0, 0, 1)
    cases = []
    for r in (0.0, 1e-4, 0.5, 1.0):
        for m in (0.0, 1.0):
            for co in (1e-6, 1e-3, 0.5, 1.0):
                for ci in (1e-6, 0.3, 1.0):
                    cases.append((r, m, co, ci))
    c = np.array(cases)                                                     # [K, 4]
    k = len(c)
    wo = np.stack([np.sqrt(1 - c[:, 2] ** 2), 0 * c[:, 2], c[:, 2]], 1)     # [K, 3]
    wi = np.stack([-np.sqrt(1 - c[:, 3] ** 2), 0 * c[:, 3], c[:, 3]], 1)    # [K, 3]
    f = np3(brdf.eval_brdf(col3(1.0, k), flt(c[:, 0], k), flt(c[:, 1], k), nz,
                           vec3(wo), vec3(wi)))
    assert np.all(np.isfinite(f)) and np.all(f >= 0)
    # mirror direction at roughness 0: large (α clamp) but finite
    f_peak = np3(brdf.eval_brdf(col3(1.0, 1), flt(0.0, 1), flt(1.0, 1), nz,
                                dir_from_cos(0.8), dir_from_cos(0.8, np.pi)))
    assert np.isfinite(f_peak).all() and f_peak.min() > 1e3
    # wi or wo below / on the horizon → exactly zero
    for wo_, wi_ in [((0.6, 0, 0.8), (0.6, 0, -0.8)), ((0.6, 0, -0.8), (0.6, 0, 0.8)),
                     ((0.6, 0, 0.8), (1, 0, 0)), ((0, 0, 1), (0, 0, -1))]:
        f = np3(brdf.eval_brdf(col3(0.7, 1), flt(0.0, 1), flt(1.0, 1), nz,
                               mi.Vector3f(*wo_), mi.Vector3f(*wi_)))
        assert np.all(f == 0.0)


def test_building_blocks():
    assert np.asarray(brdf.ggx_alpha(mi.Float(0.0)))[0] == pytest.approx(brdf.ALPHA_MIN)
    assert np.asarray(brdf.ggx_alpha(mi.Float(0.5)))[0] == pytest.approx(0.25)
    f = brdf.fresnel_schlick(mi.Color3f(0.04), mi.Float([1.0, 0.0]))
    np.testing.assert_allclose(np.asarray(f.x), [0.04, 1.0], rtol=1e-6)
    # D normalisation: ∫ D(h) cos_h dω_h = 1 (uniform hemisphere MC over h)
    u = point2(np.random.default_rng(3).random((N_MC, 2)))
    h, pdf = brdf.sample_uniform_hemisphere(u)
    for alpha in (0.2, 0.6, 1.0):
        v = np.asarray(brdf.ggx_d(alpha, h.z) * h.z / pdf, dtype=np.float64)
        assert abs(v.mean() - 1.0) < 5 * v.std() / np.sqrt(N_MC) + 1e-3
    g = brdf.smith_g(0.5, mi.Float([0.0, 1.0, 0.3]), mi.Float([0.5, 1.0, -0.1]))
    np.testing.assert_allclose(np.asarray(g), [0.0, 1.0, 0.0], atol=1e-6)


def test_matches_mitsuba_microfacet(rng):
    """D, G1 and the VNDF reflection pdf agree with mi.MicrofacetDistribution (GGX);
    our G2 is height-correlated, hence ≥ Mitsuba's separable G1·G1."""
    n = 2048
    nz = np.tile([[0.0, 0.0, 1.0]], (n, 1))
    wo, wi = vec3(random_upper(rng, nz, 0.02)), vec3(random_upper(rng, nz, 0.02))
    h = dr.normalize(wo + wi)
    for alpha in (0.05, 0.3, 0.9):
        md = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, True)
        np.testing.assert_allclose(np.asarray(brdf.ggx_d(alpha, h.z)),
                                   np.asarray(md.eval(h)), rtol=1e-4)
        np.testing.assert_allclose(np.asarray(brdf.smith_g1(alpha, wo.z)),
                                   np.asarray(md.smith_g1(wo, h)), rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(np.asarray(brdf.pdf_ggx_vndf(wo, wi, alpha)),
                                   np.asarray(md.pdf(wo, h) / (4 * dr.dot(wo, h))),
                                   rtol=2e-3, atol=1e-6)
        g2 = np.asarray(brdf.smith_g(alpha, wo.z, wi.z))
        assert np.all(g2 >= np.asarray(md.G(wo, wi, h)) - 1e-6) and np.all(g2 <= 1 + 1e-6)
        lam = lambda c: 0.5 * (-1 + np.sqrt(1 + alpha**2 * (1 - c**2) / c**2))  # noqa: E731
        co, ci = np.asarray(wo.z, np.float64), np.asarray(wi.z, np.float64)
        np.testing.assert_allclose(g2, 1 / (1 + lam(co) + lam(ci)), rtol=1e-4)


def test_frame_from_normal(rng):
    nv = np.concatenate([unit(rng, 1000), [[0, 0, 1], [0, 0, -1], [1, 0, 0],
                                           [0, 1e-7, -1], [0, 0, -0.0]]])
    nv /= np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-30)
    nv[-1] = [0, 0, -1]
    n = vec3(nv)
    s, t = brdf.frame_from_normal(n)
    S, T = np3(s), np3(t)
    for a, b in ((S, T), (S, nv), (T, nv)):
        np.testing.assert_allclose(np.sum(a * b, 1), 0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(S, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(T, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(np.cross(S, T), nv, atol=1e-5)               # right-handed
    ms, mt = mi.coordinate_system(n)
    np.testing.assert_allclose(S, np3(ms), atol=1e-6)
    np.testing.assert_allclose(T, np3(mt), atol=1e-6)
    w = vec3(unit(rng, len(nv)))
    np.testing.assert_allclose(np3(brdf.to_world(n, brdf.to_local(n, w))), np3(w), atol=1e-5)


def test_samplers_edge_inputs():
    one_m = np.nextafter(np.float32(1), np.float32(0))
    u = point2([[0, 0], [0, one_m], [one_m, 0], [one_m, one_m], [0.5, 0.5], [1.0, 1.0]])
    for name, (w, pdf) in {
            "uniform": brdf.sample_uniform_hemisphere(u),
            "cosine": brdf.sample_cosine_hemisphere(u)}.items():
        W, P = np3(w), np.asarray(pdf)
        assert np.all(np.isfinite(W)) and np.all(P > 0) and np.all(W[:, 2] > 0), name
        np.testing.assert_allclose(np.linalg.norm(W, axis=1), 1, atol=1e-5)
    for alpha in (brdf.ALPHA_MIN, 0.05, 1.0):
        for cos_o in (1e-6, 0.3, 1.0):
            w, pdf = brdf.sample_ggx_vndf(u, dir_from_cos(cos_o), alpha)
            W, P = np3(w), np.asarray(pdf)
            assert np.all(np.isfinite(W)) and np.all(np.isfinite(P)) and np.all(P >= 0)
            np.testing.assert_allclose(np.linalg.norm(W, axis=1), 1, atol=1e-4)
            assert np.all((P > 0) == (W[:, 2] > 0))


def _radical_inverse_ref(i):
    b = format(i, "b")[::-1]
    return sum(int(c) * 2.0 ** -(k + 1) for k, c in enumerate(b)) if i else 0.0


def test_hammersley():
    for n in (1, 7, 128, 1000):
        h = brdf.hammersley(n)
        assert h.shape == (n, 2) and h.dtype == np.float64
        np.testing.assert_array_equal(h[:, 0], np.arange(n) / n)
        np.testing.assert_array_equal(h[:, 1], [_radical_inverse_ref(i) for i in range(n)])
        assert np.all((h >= 0) & (h < 1))
    # power-of-two sets are stratified in y: every [k/n, (k+1)/n) holds exactly one point
    y = brdf.hammersley(256)[:, 1]
    assert np.array_equal(np.sort(np.floor(y * 256)), np.arange(256))
    with pytest.raises(ValueError):
        brdf.hammersley(0)


def test_rotated_hammersley():
    h = brdf.hammersley(256)
    a, b, c = (brdf.rotated_hammersley(256, s) for s in (0, 1, 0))
    np.testing.assert_array_equal(a, c)                        # deterministic per seed
    assert not np.allclose(a, b)                               # re-randomised per seed
    for r in (a, b):
        assert r.shape == (256, 2)
        assert np.all((r >= 0) & (r < 1))
        assert np.all((r.astype(np.float32) >= 0) & (r.astype(np.float32) < 1))
        d = np.mod(r - h, 1.0)                                 # constant offset per axis
        d = np.where(d > 0.5, d - 1.0, d)
        assert np.ptp(d, axis=0).max() < 1e-6
    # values just below 1 stay below 1 after a float32 cast
    for seed in range(200):
        assert brdf.rotated_hammersley(64, seed).astype(np.float32).max() < 1.0


# ---------------------------------------------------------------------------------------
# 6. Monte Carlo consistency between samplers

@pytest.mark.parametrize("r,m,cos_o", [(0.4, 0.0, 0.8), (0.7, 0.5, 0.3), (1.0, 1.0, 0.6),
                                       (0.5, 0.2, 0.1)])
def test_mc_consistency_full_brdf(r, m, cos_o):
    mu, su = _estimate("uniform", r, m, cos_o, albedo=0.8, seed=1)
    for sampler, seed in (("cosine", 2), ("vndf", 3)):
        mv, sv = _estimate(sampler, r, m, cos_o, albedo=0.8, seed=seed)
        assert abs(mv - mu) < 5 * np.hypot(su, sv), (sampler, mu, su, mv, sv)


@pytest.mark.parametrize("r,cos_o", [(0.2, 0.9), (0.3, 0.4)])
def test_mc_consistency_specular_lobe(r, cos_o):
    mu, su = _estimate("uniform", r, 1.0, cos_o, albedo=0.9, lobe="specular", seed=4)
    mv, sv = _estimate("vndf", r, 1.0, cos_o, albedo=0.9, lobe="specular", seed=5)
    assert sv < su                                             # importance sampling helps
    assert abs(mv - mu) < 5 * np.hypot(su, sv), (mu, su, mv, sv)
