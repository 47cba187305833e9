"""lighting.shading_start: the learnt capture light's start from an object's shading."""
import numpy as np
import pytest

from comgs_dr.core.octahedral import texel_directions_np
from comgs_dr.lighting.shading_start import MIN_SAMPLES, light_from_shading


def _sphere(n=3000):
    """Fibonacci normals over the whole sphere."""
    i = np.arange(n) + 0.5
    phi, t = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(t) * np.sin(phi), np.sin(t) * np.sin(phi), np.cos(phi)], -1)


D0 = np.array([0.6, -0.48, 0.64])          # unit: 0.36 + 0.2304 + 0.4096


def test_degree_one_light_is_recovered_exactly():
    """L(ω) = 1 + 0.8 ω·d0 (positive everywhere) shades a Lambertian sphere of albedo ρ with
    E(n) = π + (2π/3)·0.8 n·d0 (the cosine kernel's Â_0, Â_1, by hand); its radiance ρ/π·E
    must give back L at every texel, and halving the assumed albedo doubles the light."""
    n = _sphere()
    rho = 0.4
    E = np.pi + 2 * np.pi / 3 * 0.8 * (n @ D0)
    rgb = np.repeat((rho / np.pi * E)[:, None], 3, 1)
    rad, info = light_from_shading(n, rgb, 16, albedo=rho)
    want = 1 + 0.8 * (texel_directions_np(16) @ D0)
    assert rad.shape == (16, 16, 3) and np.allclose(rad[..., 0], rad[..., 2])   # grey
    np.testing.assert_allclose(rad[..., 0].ravel(), want, rtol=1e-4)
    assert info["fit_r2"] > 0.999 and info["samples"] == len(n)
    # E max / min over the probe normals (the axis-aligned and diagonal 26): d0 is not one
    # of them, so the ratio is below (π + 1.6π/3) / (π − 1.6π/3) = 3.29
    assert 2.0 < info["contrast"] < 3.29
    rad2, _ = light_from_shading(n, rgb, 16, albedo=rho / 2)
    np.testing.assert_allclose(rad2, 2 * rad, rtol=1e-9)


def test_compact_light_under_texture_points_at_the_light():
    """A 20° cap light (the studio's key) on a textured half-sphere of normals (what a
    camera sees): the fitted map is positive (floored), brightest within 15° of the cap,
    and reports a strong contrast."""
    rng = np.random.default_rng(0)
    n = _sphere(6000)
    n = n[n @ np.array([0.0, 0.0, 1.0]) > -0.3]                 # cameras above the object
    dirs = _sphere(20000)
    cap = (dirs @ D0 > np.cos(np.radians(20))) * 20.0 + 0.2     # radiance
    E = (np.maximum(n @ dirs.T, 0) * cap).sum(1) * 4 * np.pi / len(dirs)
    albedo = 0.5 * rng.uniform(0.6, 1.4, len(n))                # texture: noise to the fit
    rgb = (albedo / np.pi * E)[:, None] * np.array([1.0, 0.9, 0.8])
    rad, info = light_from_shading(n, rgb, 32)
    lum = rad[..., 0].ravel()
    assert (lum > 0).all() and np.isfinite(lum).all()
    best = texel_directions_np(32)[np.argmax(lum)]
    assert np.degrees(np.arccos(np.clip(best @ D0, -1, 1))) < 15
    assert info["contrast"] > 5 and 0.3 < info["fit_r2"] < 1.0


def test_bad_input_is_an_error():
    n = _sphere(MIN_SAMPLES - 1)
    with pytest.raises(ValueError, match="samples"):
        light_from_shading(n, np.ones_like(n), 8)
    n = _sphere(500)
    bad = np.ones_like(n)
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        light_from_shading(n, bad, 8)
    with pytest.raises(ValueError, match=r"\[P, 3\]"):
        light_from_shading(n, np.ones((500, 4)), 8)
    with pytest.raises(ValueError, match="no power"):
        light_from_shading(n, np.zeros_like(n), 8)
    with pytest.raises(ValueError, match="albedo"):
        light_from_shading(n, np.ones_like(n), 8, albedo=0.0)
