"""The ``octenvmap`` emitter: exact sampling (chi-square), normalisation, Mitsuba's own
integrators lit by it agree with Mitsuba's ``envmap``, parameters, errors."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core import octahedral as octa
from comgs_dr.core.equirect import equirect_uv_to_dir_np
from comgs_dr.core.hostarray import to_jit
from comgs_dr.emitters.octenvmap import OctEnvmapBase, is_octenvmap
from comgs_dr.lighting.envmap import equirect_to_oct_np, write_exr

# Mitsuba's envmap is Y-up with u = atan2(x, −z)/2π; ours is Z-up (Blender): this rotation
# maps Mitsuba's local frame onto ours (world = M · local).
MI_TO_ZUP = [[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]


def _sun_map(res=16, seed=0):
    rng = np.random.default_rng(seed)
    rad = np.exp(0.4 * rng.normal(size=(res, res, 3)))
    rad[3, res - 5] = 400.0                 # a "sun" texel
    return rad


def test_sampling_matches_pdf_chi2():
    """Mitsuba's spherical chi-square test (its pdf quadrature needs a map without a
    one-texel spike: the spike's texel-exact check is the next test)."""
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain
    rad = _sun_map(8)
    rad[3, 3] = 50.0
    em = OctEnvmapBase.from_radiance(rad)

    def sample(u, *args):
        ds, _ = em.sample_direction(dr.zeros(mi.Interaction3f), u)
        return ds.d

    def pdf(d, *args):
        ds = dr.zeros(mi.DirectionSample3f)
        ds.d = d
        return em.pdf_direction(dr.zeros(mi.Interaction3f), ds)

    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample, pdf_func=pdf,
                         sample_dim=2, sample_count=200_000, res=41, ires=16)
    assert chi2.run(), chi2.messages


def test_pdf_is_exact_per_texel_and_weight_is_radiance_over_pdf():
    """∫ pdf dω over each texel, by quadrature in the texel's own uv square (dω = J duv),
    equals the texel's sampling probability, and the samples land in texels with those
    probabilities (chi-square); a rotated map and a 400× sun texel."""
    from scipy.stats import chisquare
    R, sub = 16, 6
    rot = mi.ScalarTransform4f().rotate([0.6, 0.8, 0], 37)
    em = OctEnvmapBase.from_radiance(_sun_map(R), to_world=rot)
    c = (np.arange(R * sub) + 0.5) / (R * sub)
    u, v = np.meshgrid(c, c)
    uv = to_jit(mi.Point2f, np.stack([u.ravel(), v.ravel()]))
    d = mi.Transform4f(rot) @ octa.uv_to_dir(uv)
    ds = dr.zeros(mi.DirectionSample3f, R * R * sub * sub)
    ds.d = d
    p = np.asarray(em.pdf_direction(dr.zeros(mi.Interaction3f), ds))
    jac = np.asarray(octa.jacobian_uv(uv)) / (R * sub) ** 2
    per_texel = (p * jac).reshape(R, sub, R, sub).sum((1, 3)).ravel()
    assert abs(per_texel.sum() - 1.0) < 1e-3
    assert np.allclose(per_texel, em.sampler.pmf_np, rtol=2e-3, atol=1e-7)
    n = 200_000
    it = dr.zeros(mi.Interaction3f)
    ds, wgt = em.sample_direction(it, to_jit(mi.Point2f, np.random.default_rng(1).random((2, n))))
    t = np.floor(np.asarray(ds.uv).T * R).astype(int).clip(0, R - 1)
    counts = np.bincount(t[:, 1] * R + t[:, 0], minlength=R * R)
    expected = em.sampler.pmf_np * n
    big = expected > 5
    obs, exp = counts[big], expected[big]
    if (~big).any():
        obs, exp = np.r_[obs, counts[~big].sum()], np.r_[exp, expected[~big].sum()]
    assert chisquare(obs, exp * obs.sum() / exp.sum()).pvalue > 1e-3
    val = np.asarray(em.eval_direction(it, ds))
    assert np.allclose(np.asarray(wgt) * np.asarray(ds.pdf)[None], val, rtol=1e-4, atol=1e-6)
    # the pdf of a sampled direction is the sampled pdf (but for samples on a texel edge,
    # where float rounding may put the direction into the neighbouring texel)
    same = np.isclose(np.asarray(em.pdf_direction(it, ds)), np.asarray(ds.pdf), rtol=1e-4)
    assert same.mean() > 0.999


@pytest.mark.parametrize("integrator", ["path", "direct"])
def test_mitsuba_integrators_lit_by_it_match_mitsubas_envmap(tmp_path, integrator):
    """Same map, Mitsuba's ``envmap`` vs ours: a diffuse and a rough-metal sphere agree within
    noise (and the resampling of the map)."""
    h, w = 64, 128
    ex, ey = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    d = equirect_uv_to_dir_np(np.stack([ex.ravel(), ey.ravel()], -1)).reshape(h, w, 3)
    E = 0.3 + np.stack([np.maximum(d[..., 2], 0), 0.5 * (d[..., 0] + 1), 0.2 + 0 * d[..., 0]], -1)
    E = E + 30.0 * (np.einsum("hwc,c->hw", d, [0.6, 0.0, 0.8]) > 0.97)[..., None]   # sun
    path = write_exr(tmp_path / "env.exr", E.astype(np.float32), "equirect")
    base = {"type": "scene",
            "sensor": {"type": "perspective", "fov": 30,
                       "to_world": mi.ScalarTransform4f().look_at([0, -6, 1.5], [0, 0, 0], [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": 24, "height": 24},
                       "sampler": {"type": "independent", "sample_count": 256}},
            "a": {"type": "sphere", "center": [-0.6, 0, 0], "radius": 0.5,
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}},
            "b": {"type": "sphere", "center": [0.6, 0, 0], "radius": 0.5,
                  "bsdf": {"type": "roughconductor", "alpha": 0.3}},
            "integrator": {"type": integrator}}
    ours = mi.render(mi.load_dict({**base, "env": {"type": "octenvmap", "filename": str(path),
                                                   "resolution": 128}}), seed=1)
    ref = mi.render(mi.load_dict({**base, "env": {"type": "envmap", "filename": str(path),
                                                  "to_world": mi.ScalarTransform4f(MI_TO_ZUP)}}), seed=2)
    ours, ref = np.asarray(ours), np.asarray(ref)
    assert np.isfinite(ours).all()
    # whole-image means within 2 %, 4×4-block means within 8 % (noise at 256 spp)
    assert abs(ours.mean() / ref.mean() - 1) < 0.02, (ours.mean(), ref.mean())
    bo = ours.reshape(4, 6, 4, 6, 3).mean((1, 3))
    br = ref.reshape(4, 6, 4, 6, 3).mean((1, 3))
    assert np.all(np.abs(bo - br) <= 0.08 * br + 0.01)


def test_parameters_update_the_sampler_and_lookups():
    rad = np.ones((8, 8, 3))
    scene = mi.load_dict({"type": "scene", "env": OctEnvmapBase.from_radiance(rad)})
    em = scene.environment()
    assert is_octenvmap(em)
    p = mi.traverse(scene)
    new = np.ones((8, 8, 3), np.float32)
    new[2, 5] = 1e6                                   # HDR up to 1e6
    p["env.data"] = to_jit(mi.TensorXf, new)
    p.update()
    u = to_jit(mi.Point2f, np.random.default_rng(0).random((2, 2000)))
    ds, wgt = em.sample_direction(dr.zeros(mi.Interaction3f), u)
    texel = np.asarray(ds.uv).T * 8
    near = (np.abs(texel[:, 0].astype(int) - 5) <= 1) & (np.abs(texel[:, 1].astype(int) - 2) <= 1)
    assert near.mean() > 0.95         # sampling follows the new data (its 3×3 dilation)
    assert np.isfinite(np.asarray(wgt)).all()
    with pytest.raises(ValueError, match="non-finite"):
        bad = new.copy()
        bad[0, 0, 0] = np.nan
        p["env.data"] = to_jit(mi.TensorXf, bad)
        p.update()


def test_rotation_moves_the_map():
    rad = np.full((16, 16, 3), 0.1)
    sun = equirect_to_oct_np(np.ones((8, 16, 3)), 16) * 0     # zero map of the right shape
    sun[8, 8] = 50.0                                  # texel near +Z (centre of the square)
    em = OctEnvmapBase.from_radiance(rad + sun, to_world=mi.ScalarTransform4f().rotate([1, 0, 0], 90))
    up = np.asarray(em.eval_world(mi.Vector3f(0, 0, 1)))
    rotated = np.asarray(em.eval_world(mi.Vector3f(0, -1, 0)))      # +Z rotated about +X
    assert rotated.max() > 10 * up.max()


def test_clear_errors():
    with pytest.raises(Exception, match="filename"):
        mi.load_dict({"type": "octenvmap"})
    with pytest.raises(ValueError, match=r"\[R, R, 3\]"):
        OctEnvmapBase.from_radiance(np.ones((4, 8, 3)))
    with pytest.raises(ValueError, match="finite"):
        OctEnvmapBase.from_radiance(np.full((4, 4, 3), np.inf))
    with pytest.raises(ValueError, match="rotation"):
        OctEnvmapBase.from_radiance(np.ones((4, 4, 3)), to_world=mi.ScalarTransform4f().scale(2))
