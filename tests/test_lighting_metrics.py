"""Array-of-spheres renders and lighting metrics (comgs_dr.eval.lighting_metrics)."""
from math import pi

import numpy as np
import pytest

from comgs_dr.core.equirect import (
    equirect_dir_to_uv_np,
    equirect_directions,
    pixel_solid_angles,
)
from comgs_dr.core.hostarray import to_jit
from comgs_dr.eval import lighting_metrics as lm


def smooth_map(h=64):
    """Order ≤ 2 map in three channels: L = a + b·d + c·P2(d_z) (closed-form irradiance)."""
    d = equirect_directions(h, 2 * h)
    a, b, c = np.array([1.0, 2.0, 0.5]), np.array([0.3, -0.2, 0.5]), np.array([0.4, 0.1, -0.2])
    p2 = (3 * d[..., 2:] ** 2 - 1) / 2
    return a + (d @ b)[..., None] * np.array([1.0, 0.5, 0.2]) + c * p2, (a, b, c)


def mc_specular(n, c, radiance, m=1_000_000, seed=0):
    """Brute Monte-Carlo ∫ f_spec L cos dω with uniform hemisphere samples: (mean, std err)."""
    rng = np.random.default_rng(seed)
    u = rng.random((m, 2))
    z = 1.0 - u[:, 0]
    r, ph = np.sqrt(1 - z * z), 2 * pi * u[:, 1]
    t1 = np.cross(n, [0, 0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [1.0, 0, 0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    wi = (r * np.cos(ph))[:, None] * t1 + (r * np.sin(ph))[:, None] * t2 + z[:, None] * n
    co, ci = float(n @ c), wi @ n
    cd = np.sqrt(np.maximum(0.5 + 0.5 * wi @ c, 0))
    ch = np.minimum((co + ci) / (2 * cd), 1)
    a, b = lm.ggx_specular_np(lm.SILVER_ROUGHNESS, co, ci, cd, ch)
    f = (lm.SILVER_F0 * a[:, None] + (1 - lm.SILVER_F0) * (a * b)[:, None]) * ci[:, None]
    f = f * 2 * pi * radiance(wi)
    return f.mean(0), f.std(0) / np.sqrt(m)


class TestMetrics:
    def test_si_rmse_scale_invariance(self, rng):
        gt = rng.random((8, 8, 3))
        est = gt + 0.1 * rng.random((8, 8, 3))
        mask = rng.random((8, 8)) > 0.3
        v = lm.si_rmse(est, gt, mask)
        assert v > 0
        for s in (1e-3, 0.5, 7.0, 1e6):
            assert lm.si_rmse(s * est, gt, mask) == pytest.approx(v, rel=1e-9)
        assert lm.si_rmse(3.7 * gt, gt, mask) == pytest.approx(0.0, abs=1e-12)
        # closed form equals a brute search over α
        m = mask
        alphas = np.linspace(0.5, 1.5, 20001)
        brute = min(np.sqrt(np.mean((a * est[m] - gt[m]) ** 2)) for a in alphas)
        assert v == pytest.approx(brute, rel=1e-6)

    def test_angular_error(self, rng):
        gt = rng.random((6, 6, 3)) + 0.1
        assert lm.angular_error_deg(5.0 * gt, gt) == pytest.approx(0.0, abs=1e-5)
        red, green = np.zeros((4, 4, 3)), np.zeros((4, 4, 3))
        red[..., 0], green[..., 1] = 1.0, 2.0
        assert lm.angular_error_deg(red, green) == pytest.approx(90.0)
        # zero norms: both zero -> 0°, one zero -> 90°
        z = np.zeros((2, 1, 3))
        one = np.array([[[0.0, 0, 0]], [[1.0, 1, 1]]])
        assert lm.angular_error_deg(z, z) == 0.0
        assert lm.angular_error_deg(one, z) == pytest.approx(45.0)

    def test_nrmse(self, rng):
        gt = rng.random((5, 5, 3)) + 0.1
        assert lm.nrmse(gt, gt) == 0.0
        assert lm.nrmse(np.zeros_like(gt), gt) == pytest.approx(1.0)
        assert lm.nrmse(1.1 * gt, gt) == pytest.approx(0.1)

    def test_extreme_values_finite(self, rng):
        gt = rng.random((8, 8, 3))
        gt[3, 4] = 1e6
        est = rng.random((8, 8, 3)) * 1e6
        for f in (lm.si_rmse, lm.angular_error_deg, lm.nrmse):
            assert np.isfinite(f(est, gt))
            assert np.isfinite(f(np.zeros_like(gt), gt))
            assert np.isfinite(f(est * 1e300, gt * 1e300))
        assert lm.si_rmse(np.zeros_like(gt), np.zeros_like(gt)) == 0.0
        assert lm.nrmse(np.zeros_like(gt), np.zeros_like(gt)) == 0.0

    def test_errors(self, rng):
        a = rng.random((4, 4, 3))
        bad = a.copy()
        bad[0, 0, 0] = np.nan
        for f in (lm.si_rmse, lm.angular_error_deg, lm.nrmse):
            with pytest.raises(ValueError, match="NaN"):
                f(bad, a)
            with pytest.raises(ValueError, match="shape"):
                f(a, a[:3])
            with pytest.raises(ValueError, match="mask"):
                f(a, a, np.ones((3, 3)))
            with pytest.raises(ValueError, match="no pixel"):
                f(a, a, np.zeros((4, 4)))
        with pytest.raises(ValueError, match="material"):
            lm.render_sphere(a, "gold")
        with pytest.raises(ValueError, match="NaN"):
            lm.render_sphere(np.full((8, 16, 3), np.nan))


class TestSpheres:
    def test_area_resize_preserves_energy(self, rng):
        env = rng.random((24, 48, 3)) ** 4
        env[5, 7] = 1e6
        for h, w in ((8, 16), (10, 20), (7, 13), (48, 96)):
            small = lm.area_resize_equirect(env, h, w)
            e0 = (env * pixel_solid_angles(24, 48)[..., None]).sum((0, 1))
            e1 = (small * pixel_solid_angles(h, w)[..., None]).sum((0, 1))
            np.testing.assert_allclose(e1, e0, rtol=1e-10)

    def test_white_furnace_diffuse(self):
        """Constant map L: the diffuse sphere is albedo·L everywhere (row normalisation)."""
        L = np.array([0.3, 1.0, 2.5])
        img, mask = lm.render_sphere(np.broadcast_to(L, (16, 32, 3)), "diffuse", 32,
                                     lm.ARRAY_AZIMUTHS)
        np.testing.assert_allclose(img[:, mask], np.broadcast_to(lm.DIFFUSE_ALBEDO * L,
                                                                 img[:, mask].shape), rtol=1e-6)
        assert (img[:, ~mask] == 0).all()

    def test_diffuse_matches_sh_irradiance(self):
        """Order-2 map: E(n) = π a + (2π/3) b·n + (π/4) c P2(n_z) exactly (Ramamoorthi &
        Hanrahan); quadrature error at q = 32 measured ≈ 3e-4, tolerance 2e-3 absolute."""
        env, (a, b, c) = smooth_map()
        img, mask = lm.render_sphere(env, "diffuse", 48, lm.ARRAY_AZIMUTHS)
        for i, az in enumerate(lm.ARRAY_AZIMUTHS):   # every view: also checks the map roll
            n = lm.sphere_geometry(48, az)[0][mask]
            e = (pi * a + (2 * pi / 3) * (n @ b)[:, None] * np.array([1.0, 0.5, 0.2])
                 + (pi / 4) * c * ((3 * n[:, 2:] ** 2 - 1) / 2))
            np.testing.assert_allclose(img[i][mask], lm.DIFFUSE_ALBEDO / pi * e, atol=2e-3)

    def test_non_grid_azimuth_matches_rolled(self):
        """Azimuth 30° at q = 16 is not a whole-column roll: it builds its own operator;
        compared with the closed form as above (coarser grid: 5e-3)."""
        env, (a, b, c) = smooth_map(32)
        img, mask = lm.render_sphere(env, "diffuse", 32, (30.0,), quad_height=16)
        n = lm.sphere_geometry(32, 30.0)[0][mask]
        e = (pi * a + (2 * pi / 3) * (n @ b)[:, None] * np.array([1.0, 0.5, 0.2])
             + (pi / 4) * c * ((3 * n[:, 2:] ** 2 - 1) / 2))
        np.testing.assert_allclose(img[0][mask], lm.DIFFUSE_ALBEDO / pi * e, atol=5e-3)

    def test_mirror_round_trip(self):
        """Mirror pixels equal the map at the reflection direction of an independent
        geometry (linear map in d: bilinear lookups are exact up to the v clamp/seam)."""
        h = 64
        d = equirect_directions(h, 2 * h)
        env = 0.5 + 0.5 * d                          # [H, W, 3], colour = direction
        img, mask = lm.render_sphere(env, "mirror", 32, (0.0,))
        # centre of the default camera (on −Y) reflects −Y
        t = (np.arange(32) + 0.5) / 16 - 1
        sx, sy = np.meshgrid(t, -t)
        sz = np.sqrt(np.maximum(1 - sx ** 2 - sy ** 2, 0))
        n = np.stack([sx, -sz, sy], -1)              # right = +X, toward camera = −Y, up = +Z
        r = 2 * n[..., 1:2] * -1 * n - np.array([0, -1.0, 0])
        ok = mask & (np.abs(r[..., 2]) < 0.95)       # away from the poles (v clamping)
        np.testing.assert_allclose(img[0][ok], 0.5 + 0.5 * r[ok], atol=0.02)
        # a bright patch at a known direction appears where the sphere reflects it
        env = np.full((h, 2 * h, 3), 0.1)
        target = np.array([0.6, -0.6, 0.52])
        target /= np.linalg.norm(target)
        uv = equirect_dir_to_uv_np(target[None])[0]
        env[int(uv[1] * h), int(uv[0] * 2 * h)] = 1e6           # a 1e6 "sun" pixel
        img, mask = lm.render_sphere(env, "mirror", 64, (0.0,))
        assert np.isfinite(img).all()
        i, j = np.unravel_index(np.argmax(img[0, ..., 0]), mask.shape)
        nn, c, _ = lm.sphere_geometry(64)
        refl = 2 * (nn[i, j] @ c) * nn[i, j] - c
        assert np.degrees(np.arccos(np.clip(refl @ target, -1, 1))) < 6.0   # pixel ≈ 2.8°

    def test_matte_silver_constant_map_is_albedo(self):
        """Constant map: glossy pixels equal the directional albedo, checked against brute
        Monte Carlo (1e6 uniform-hemisphere samples); tolerance 4σ + 5e-3 (table
        interpolation in μ and its 2048-point Hammersley quadrature)."""
        img, mask = lm.render_sphere(np.ones((16, 32, 3)), "matte_silver", 32, (0.0,))
        n, c, _ = lm.sphere_geometry(32)
        for (i, j) in [(16, 16), (4, 12), (25, 28), (16, 1)]:
            assert mask[i, j]
            mean, se = mc_specular(n[i, j], c, lambda w: np.ones((len(w), 1)), seed=i)
            assert np.all(np.abs(img[0, i, j] - mean) < 4 * se + 5e-3), (i, j, img[0, i, j],
                                                                           mean, se)

    def test_matte_silver_smooth_map_matches_mc(self):
        """Smooth map: quadrature (q = 32) vs brute MC; measured within ~1σ; tolerance
        4σ + 1 % relative."""
        env, (a, b, c0) = smooth_map()
        img, mask = lm.render_sphere(env, "matte_silver", 32, (90.0,))
        n, c, _ = lm.sphere_geometry(32, 90.0)

        def radiance(w):
            return a + (w @ b)[:, None] * np.array([1.0, 0.5, 0.2]) \
                + c0 * ((3 * w[:, 2:] ** 2 - 1) / 2)
        for (i, j) in [(16, 16), (6, 14)]:
            mean, se = mc_specular(n[i, j], c, radiance, seed=j)
            assert np.all(np.abs(img[0, i, j] - mean) < 4 * se + 0.01 * np.abs(mean))

    def test_numpy_ggx_matches_project_brdf(self, variant, rng):
        """ggx_specular_np reproduces shading.brdf.eval_brdf_split (float32 Dr.Jit)."""
        import mitsuba as mi

        from comgs_dr.shading import brdf
        k = 500
        wo, wi = rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
        wo[:, 2], wi[:, 2] = np.abs(wo[:, 2]), np.abs(wi[:, 2])
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        wi /= np.linalg.norm(wi, axis=1, keepdims=True)

        def vec(x):
            return to_jit(mi.Vector3f, x.T)
        f0 = [float(x) for x in lm.SILVER_F0]
        _, spec = brdf.eval_brdf_split(mi.Color3f(*f0), mi.Float(lm.SILVER_ROUGHNESS),
                                       mi.Float(1.0), vec(np.tile([0, 0, 1.0], (k, 1))),
                                       vec(wo), vec(wi))
        spec = np.array(spec)
        spec = spec.T if spec.shape[0] == 3 else spec
        co, ci = wo[:, 2], wi[:, 2]
        cd = np.sqrt(np.maximum(0.5 + 0.5 * (wo * wi).sum(1), 0))
        a, b = lm.ggx_specular_np(lm.SILVER_ROUGHNESS, co, ci, cd, np.minimum((co + ci) /
                                                                              (2 * cd), 1))
        ref = lm.SILVER_F0 * a[:, None] + (1 - lm.SILVER_F0) * (a * b)[:, None]
        np.testing.assert_allclose(spec, ref, rtol=2e-3, atol=1e-4)

    def test_sun_pixel_all_materials_finite(self):
        env = np.full((32, 64, 3), 0.2)
        env[8, 20] = 1e6
        renders, mask = lm.render_spheres(env, size=24)
        for m, img in renders.items():
            assert np.isfinite(img).all() and img[:, mask].max() > 0.2, m
        gt = renders
        est, _ = lm.render_spheres(np.full((32, 64, 3), 0.2), size=24)
        res = lm.sphere_metrics(est, gt, mask)
        assert all(np.isfinite(v) for d in res.values() for v in d.values())


def test_irradiance_contrast_flat_map_and_a_sun():
    """1 for a flat light; a small bright source on a dim sky: the facing / the opposite
    irradiance, (π·L_sky + E_sun) / (π·L_sky) by hand."""
    from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles
    from comgs_dr.eval.lighting_metrics import irradiance_contrast
    flat = np.full((32, 64, 3), 0.7)
    assert irradiance_contrast(flat, normals=400) == pytest.approx(1.0, abs=0.02)
    sun = flat * 0 + 0.1
    d = equirect_directions(32, 64)
    disk = d @ np.array([0.0, 0.0, 1.0]) > np.cos(np.radians(12.0))
    sun[disk] = 50.0
    e_sun = 50.0 * (pixel_solid_angles(32, 64) * d[..., 2])[disk].sum()
    want = (np.pi * 0.1 + e_sun) / (np.pi * 0.1)
    assert irradiance_contrast(sun, normals=400) == pytest.approx(want, rel=0.1)
    with pytest.raises(ValueError, match="NaN"):
        irradiance_contrast(np.full((8, 16, 3), np.nan))
