"""The dominant compact source split off a map (shading.sun) and the shadow ratio that
traces it (shading.shadow with ``sun=``): the split is exact, the estimate unbiased."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core import octahedral as octa
from comgs_dr.core.hostarray import to_jit
from comgs_dr.emitters.octenvmap import OctEnvmapBase
from comgs_dr.shading.shadow import shadow_ratio
from comgs_dr.shading.sun import find_sun, split_sun
from comgs_dr.shading.visibility import NoVisibility

SUN = np.array([0.5, 0.3, 0.4]) / np.linalg.norm([0.5, 0.3, 0.4])


def sky_and_sun(res=128, sky=0.5, sun=3000.0, radius_deg=2.0, direction=SUN):
    d = octa.texel_directions_np(res).reshape(res, res, 3)
    m = np.repeat((sky * (1.0 + np.maximum(d[..., 2], 0.0)))[..., None], 3, -1)
    if sun:
        m[(d @ direction) > np.cos(np.radians(radius_deg))] = sun
    return m


class Cone:
    """O = 1 inside a cone (an occluder of known shape)."""
    name = "cone"

    def __init__(self, axis, half_deg):
        self.axis, self.cos = np.asarray(axis, float), float(np.cos(np.radians(half_deg)))

    def prepare(self, pts):
        pass

    def lookup(self, pid, wi, need_radiance):
        a = mi.Vector3f(*map(float, self.axis))
        return dr.select(dr.dot(wi, a) > self.cos, 1.0, 0.0), None


def test_find_sun_locates_the_disk_and_refuses_a_smooth_sky():
    m = sky_and_sun()
    mask, d, share, radius = find_sun(m)
    assert np.degrees(np.arccos(np.clip(d @ SUN, -1, 1))) < 0.5
    assert 1.0 < radius < 3.0                          # a 2° disk on 1.4° texels
    # analytic share: E_sun = L_sun Ω cosθ≈1 against the sky's cosine-weighted irradiance
    res = 128
    dirs = octa.texel_directions_np(res)
    dw = octa.texel_solid_angles_np(res).ravel()
    lum = m.reshape(-1, 3)[:, 0]
    facing = np.maximum(dirs @ d, 0) * lum * dw
    assert share == pytest.approx((facing * mask.ravel()).sum() / facing.sum())
    assert 0.75 < share < 0.9                          # 11.5 of ≈ 14 (sky ≈ 2.4)
    assert find_sun(sky_and_sun(sun=0.0)) is None     # no compact source: nothing split
    assert find_sun(np.zeros((16, 16, 3))) is None


def test_split_maps_sum_to_the_original_everywhere():
    env = OctEnvmapBase.from_radiance(sky_and_sun())
    sp = split_sun(env)
    assert sp is not None and sp.share > 0.75
    rng = np.random.default_rng(0)
    v = rng.normal(size=(3, 4000))
    v /= np.linalg.norm(v, axis=0)
    v[:, :2000] = SUN[:, None] + 0.05 * v[:, :2000]      # half near the sun's edge
    v /= np.linalg.norm(v, axis=0)
    d = to_jit(mi.Vector3f, v)
    whole = np.asarray(env.eval_world(d))
    parts = np.asarray(sp.sun.eval_world(d)) + np.asarray(sp.rest.eval_world(d))
    np.testing.assert_allclose(parts, whole, rtol=1e-5, atol=1e-4)


def reference_ratio(env, axis, cone_deg, n=2_000_000):
    """L_o'/L_o by quadrature on a Fibonacci sphere of ``n`` directions (the map's own
    bilinear radiance; a 2° sun gets ~600 of them), normal +Z."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5 ** 0.5) * i
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z])
    d = d[:, z > 0]
    L = np.asarray(env.eval_world(to_jit(mi.Vector3f, d)))[0] * d[2]
    lit = L * ~((axis @ d) > np.cos(np.radians(cone_deg)))
    return lit.sum() / L.sum()


@pytest.mark.parametrize("cone_deg", [1.0, 3.0, 30.0])
def test_split_shadow_ratio_matches_quadrature(cone_deg):
    """A blocker covering part of the sun (1°), all of it (3°) or sun and sky (30°): the
    split estimate (sun rays traced through the same blocker) converges to the quadrature."""
    res = 128
    m = sky_and_sun(res)
    env = OctEnvmapBase.from_radiance(m)
    sp = split_sun(env)
    n = 256
    x = to_jit(mi.Point3f, np.zeros((3, n)))
    nz = to_jit(mi.Vector3f, np.stack([np.zeros(n), np.zeros(n), np.ones(n)]))
    blocker = Cone(SUN, cone_deg)
    want = reference_ratio(env, SUN, cone_deg)
    S = np.asarray(shadow_ratio(x, nz, env, blocker, rays=64, seed=1, sun=sp,
                                sun_visibility=blocker, sun_rays=64))[0]
    assert np.all((S >= 0) & (S <= 1))
    assert abs(S.mean() - want) < 0.02, (S.mean(), want)
    # the split lowers the per-pixel noise of the sun's shadow at equal rays
    S_plain = np.asarray(shadow_ratio(x, nz, env, blocker, rays=128, seed=1))[0]
    assert abs(S_plain.mean() - want) < 0.05
    if cone_deg == 1.0:
        assert S.std() < S_plain.std(), (S.std(), S_plain.std())


def test_split_shadow_ratio_is_one_unoccluded_and_refuses_a_missing_tracer():
    env = OctEnvmapBase.from_radiance(sky_and_sun(64))
    sp = split_sun(env)
    x = to_jit(mi.Point3f, np.zeros((3, 8)))
    nz = to_jit(mi.Vector3f, np.stack([np.zeros(8), np.zeros(8), np.ones(8)]))
    S = np.asarray(shadow_ratio(x, nz, env, NoVisibility(), rays=16, sun=sp,
                                sun_visibility=NoVisibility(), sun_rays=4))
    np.testing.assert_allclose(S, 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="sun_visibility"):
        shadow_ratio(x, nz, env, NoVisibility(), rays=16, sun=sp)
