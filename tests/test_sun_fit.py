"""The sun from the scene's own cast shadows (lighting.sun_fit): a ground with a block whose
surfel colours are a known sun's shading (visibility from the analytic box, not from our
tracer), and the same ground with no caster; the fusion into a panorama."""
import numpy as np
import pytest

from comgs_dr.lighting import sun_fit as sf

SUN = np.array([np.cos(np.radians(35)) * np.cos(np.radians(40)),
                np.cos(np.radians(35)) * np.sin(np.radians(40)), np.sin(np.radians(35))])
K_TRUE = 4.0
LO, HI = np.array([-0.25, -0.25, 0.0]), np.array([0.25, 0.25, 0.6])


def _box_hit(o, d, boxes=((LO, HI),)):
    """[N] bool: the rays o + t d (t > 0) hit any of the axis-aligned ``boxes``."""
    inv = 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)
    hit = np.zeros(len(o), bool)
    for lo, hi in boxes:
        t0, t1 = (np.asarray(lo) - o) * inv, (np.asarray(hi) - o) * inv
        t_near, t_far = np.minimum(t0, t1).max(1), np.maximum(t0, t1).min(1)
        hit |= t_far > np.maximum(t_near, 0.0)
    return hit


def _surfel_scene(boxes, sun, k, n_surfels, seed, gain, outward):
    """Surfels of a textured 3×3 ground and the axis-aligned ``boxes`` shaded by ``sun`` and
    a uniform sky: L = gain · ρ/π (a + k V cos), a the sky's visible fraction past the boxes
    (cosine-weighted, 64 directions), V the sun's from the analytic boxes (not our tracer).
    ``outward``: the boxes' side faces get outward normals (else only flipped to face up)."""
    import trimesh

    from comgs_dr.core.colorspace import srgb_encode
    from comgs_dr.surfels.from_mesh import from_mesh
    from comgs_dr.surfels.io import quat_to_matrix
    from comgs_dr.surfels.kernel import SH_C0
    from comgs_dr.surfels.params import SurfelParams
    from comgs_dr.surfels.scene import gbuffer_scene
    parts = [trimesh.Trimesh([[-1.5, -1.5, 0], [1.5, -1.5, 0], [1.5, 1.5, 0], [-1.5, 1.5, 0]],
                             [[0, 1, 2], [0, 2, 3]])]
    for lo, hi in boxes:
        lo, hi = np.asarray(lo), np.asarray(hi)
        parts.append(trimesh.creation.box(extents=hi - lo).apply_translation((lo + hi) / 2))
    d = from_mesh(trimesh.util.concatenate(parts), n_surfels, seed=seed, opacity=0.99).to_numpy()
    x = d["means"].astype(np.float64)
    n = quat_to_matrix(d["quats"])[:, :, 2]
    n *= np.where(n[:, 2:3] < 0, -1.0, 1.0)
    for lo, hi in boxes if outward else ():
        lo, hi = np.asarray(lo), np.asarray(hi)
        on = np.all((x >= lo - 1e-4) & (x <= hi + 1e-4), 1) & (np.abs(n[:, 2]) < 0.5)
        n[on] *= np.sign(((x[on] - (lo + hi) / 2) * n[on]).sum(1))[:, None]
    V, sky = np.ones(len(x)), np.ones(len(x))
    if boxes:
        V = ~_box_hit(x + 1e-3 * n, np.tile(sun, (len(x), 1)), boxes)
        dirs = sf.fibonacci_hemisphere(64)
        w = np.maximum(n @ dirs.T, 0.0)
        seen = np.stack([~_box_hit(x + 1e-3 * n, np.tile(q, (len(x), 1)), boxes)
                         for q in dirs], 1)
        sky = (w * seen).sum(1) / np.maximum(w.sum(1), 1e-12)
    rho = np.random.default_rng(seed).uniform(0.25, 0.6, (len(x), 1)) * [[1.0, 0.9, 0.8]]
    L = rho / np.pi * (sky + k * V * np.maximum(n @ sun, 0))[:, None] * gain
    d["sh"][:, 0] = (srgb_encode(np.clip(L, 0, 1)) - 0.5) / SH_C0
    p = SurfelParams.from_numpy(**d)
    return gbuffer_scene({"scene": p}, [], targets="weight"), p


def _scene(caster: bool, seed=0, boxes=((LO, HI),)):
    """A ground (+ the block) under SUN, k = K_TRUE (:func:`_surfel_scene`)."""
    return _surfel_scene(boxes if caster else (), SUN, K_TRUE, 9000, seed, 0.5, False)


CFG = sf.SunFitConfig(points=2000, directions=96, refine=24)


def test_the_sun_is_found_from_a_block_shadow_and_not_invented_without_one():
    sc, p = _scene(True)
    fit = sf.fit_sun_in_scene(sc, p, "srgb", CFG)
    assert fit.usable, fit.reason
    # measured 4.8° and k 4.73 (+18 %) with these 2000 receivers (4.1° / 4.51 before the
    # walls' receivers and the shadow's core)
    assert np.degrees(np.arccos(np.clip(fit.direction @ SUN, -1, 1))) < 6.0
    assert fit.k == pytest.approx(K_TRUE, rel=0.25)
    np.testing.assert_allclose(fit.k_rgb, fit.k, rtol=0.05)       # a grey sun over a grey sky
    assert 0.02 < fit.shadowed < 0.2 and fit.z > 2 * fit.rival
    sc, p = _scene(False)
    none = sf.fit_sun_in_scene(sc, p, "srgb", CFG)
    assert not none.usable and "no usable cast shadow" in none.reason


def test_several_casters_agree_on_one_sun():
    """A tall thin post and a low wide slab: two shadows of different shapes, one sun
    (measured 5.2° and k 3.72; 4.2° and 4.27 before the walls' receivers and the shadow's
    core)."""
    boxes = (((-0.9, 0.5, 0.0), (-0.8, 0.6, 0.8)), ((0.3, -0.6, 0.0), (0.9, -0.2, 0.25)))
    sc, p = _scene(True, seed=1, boxes=boxes)
    fit = sf.fit_sun_in_scene(sc, p, "srgb", CFG)
    assert fit.usable, fit.reason
    assert np.degrees(np.arccos(np.clip(fit.direction @ SUN, -1, 1))) < 6.0
    assert fit.k == pytest.approx(K_TRUE, rel=0.25)


def test_add_sun_supplies_what_the_panorama_did_not_see():
    from comgs_dr.core.equirect import equirect_directions, solid_angle_image
    h, w = 64, 128
    dirs = equirect_directions(h, w)
    sky = np.where(dirs[..., 2:3] > 0, 0.5, 0.1) * np.ones(3)
    guessed = sky.copy()
    guessed[(dirs @ -SUN) > np.cos(np.radians(8)) - 1 + 1] = 1.0        # no-op guard
    far = _unit(np.array([-0.6, -0.4, 0.5]))
    guessed[(dirs @ far) > np.cos(np.radians(5))] = 40.0               # a guessed sun elsewhere
    fit = sf.SunFit(SUN, 3.0, np.array([3.0, 3.0, 3.0]), 20.0, 5.0, 0.1, True, "", 100, 0.0)
    unseen = np.zeros((h, w), bool)
    out, what = sf.add_sun(guessed, unseen, fit, radius_deg=2.0, unseen_sky="completion")
    assert what.startswith("added")
    assert out[(dirs @ far) > np.cos(np.radians(5))].max() == pytest.approx(0.5)
    e_up = sf.up_irradiance(sky)
    cos = np.maximum(dirs @ SUN, 0) * solid_angle_image(h, w)
    e_sun = np.einsum("hwc,hw->c", out - sky, cos)
    np.testing.assert_allclose(e_sun, 3.0 * e_up * (SUN @ SUN), rtol=0.1)   # k × E_up, facing d
    seen = np.ones((h, w), bool)
    kept, what = sf.add_sun(guessed, seen, fit)
    assert kept is guessed and what.startswith("kept")


def _unit(v):
    return v / np.linalg.norm(v)


def test_the_unseen_sky_becomes_a_clear_sky_for_the_fitted_sun():
    """The completion's warm guess of a sky nobody saw is replaced by a clear sky for the
    sun (blue overhead, brightest toward the sun), at the guess's irradiance on the ground;
    the observed pixels (here the lower hemisphere and one patch of sky) are kept."""
    from comgs_dr.core.colorspace import LUMA
    from comgs_dr.core.equirect import equirect_directions, solid_angle_image
    h, w = 64, 128
    dirs = equirect_directions(h, w)
    guess = np.where(dirs[..., 2:3] > 0, [0.9, 0.6, 0.3], [0.2, 0.15, 0.1])   # warm
    observed = dirs[..., 2] <= 0
    patch = (dirs @ _unit(np.array([-1.0, 0.0, 0.3]))) > np.cos(np.radians(15))
    observed |= patch
    low = _unit(np.array([0.8, -0.58, 0.15]))                                 # 8.6° high
    fit = sf.SunFit(low, 3.0, np.array([4.0, 3.0, 2.0]), 20.0, 5.0, 0.1, True, "", 100, 0.0)
    sky_only, _ = sf.add_sun(guess, observed, fit, radius_deg=1e-3)
    np.testing.assert_allclose(sky_only[observed], guess[observed], rtol=1e-6)
    unseen = ~observed & (dirs[..., 2] > 0)
    wgt = solid_angle_image(h, w) * np.maximum(dirs[..., 2], 0)
    e_before = ((guess @ LUMA) * wgt)[unseen].sum()
    near = (dirs @ low) > np.cos(np.radians(4.0))
    e_after = ((sky_only @ LUMA) * wgt)[unseen & ~near].sum()
    assert e_after <= e_before * 1.001
    assert e_after >= e_before * 0.97                 # the sun's disk is the rest
    zenith = sky_only[dirs[..., 2] > 0.95].mean(0)
    assert zenith[2] > 1.2 * zenith[0]                  # blue overhead, not the guess's warm
    sky = np.where(unseen & ~near, sky_only @ LUMA, 0)
    top = dirs.reshape(-1, 3)[np.argmax(sky)]
    assert np.degrees(np.arccos(top @ low)) < 25        # brightest toward the sun
    kept, _ = sf.add_sun(guess, observed, fit, radius_deg=1e-3, unseen_sky="completion")
    np.testing.assert_allclose(kept[unseen & ~near], guess[unseen & ~near], rtol=1e-6)
    with pytest.raises(ValueError, match="unseen_sky"):
        sf.add_sun(guess, observed, fit, unseen_sky="blue")


def test_clear_sky_checks_and_horizon():
    from comgs_dr.core.equirect import equirect_directions
    from comgs_dr.lighting import clear_sky
    dirs = equirect_directions(16, 32)
    m = clear_sky.clear_sky([1.0, 0.0, -0.2], 16, 32)          # below the horizon: lifted
    assert np.isfinite(m).all() and (m[dirs[..., 2] <= 0] == 0).all()
    assert (m[dirs[..., 2] > 0.1] > 0).all()
    for bad in ([0, 0, 0], [np.nan, 0, 1]):
        with pytest.raises(ValueError, match="direction"):
            clear_sky.clear_sky(bad, 8, 16)
    with pytest.raises(ValueError, match="turbidity"):
        clear_sky.clear_sky([0, 0, 1], 8, 16, turbidity=20)
    flat = np.ones((16, 32, 3))
    same, scale = clear_sky.fill_unseen_sky(flat, np.zeros((16, 32), bool), [0, 0, 1])
    assert scale == 0.0 and (same == flat).all()


def test_grid_and_config_checks():
    d = sf.fibonacci_hemisphere(200, 5.0)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert d[:, 2].min() >= np.sin(np.radians(5.0)) - 1e-12
    with pytest.raises(ValueError, match="radius_frac"):
        sf.SunFitConfig(radius_frac=0.0).validate()
    from comgs_dr.stages.estimate_light import EstimateConfig
    with pytest.raises(ValueError, match="sun_from_shadows"):
        EstimateConfig(sun_from_shadows="maybe").validate()
    with pytest.raises(ValueError, match="sun_radius_deg"):
        EstimateConfig(sun_radius_deg=0.0).validate()
    with pytest.raises(ValueError, match="unseen_sky"):
        EstimateConfig(unseen_sky="blue").validate()
    with pytest.raises(ValueError, match="sky_turbidity"):
        EstimateConfig(sky_turbidity=0.5).validate()
    with pytest.raises(ValueError, match="max_ground_albedo"):
        EstimateConfig(max_ground_albedo=1.5).validate()
    few = sf.fit_sun(np.zeros((10, 3)), np.tile([0, 0, 1.0], (10, 1)), np.ones((10, 3)),
                     lambda d: np.ones(10))
    assert not few.usable and "receivers" in few.reason


def test_a_seen_sun_gets_its_power_and_colour_from_the_shadows():
    """The sun's direction known (the panorama saw it): k per channel from the shadows
    toward it; a colour cast of the whole ground (the albedo) is no shadow and changes
    nothing; a wrong direction finds no shadow."""
    sc, p = _scene(True)
    x, n, L, vis = sf.scene_receivers(sc, p, "srgb", CFG)
    warm = np.array([1.0, 0.8, 0.5])
    at = sf.fit_sun(x, n, L * (1.0 + K_TRUE * warm) / (1.0 + K_TRUE), vis, CFG,
                    direction=SUN)       # a colour cast that is not a shadow: no effect on k
    assert at.usable and "seen sun" in at.reason
    np.testing.assert_allclose(at.direction, SUN)
    assert at.k == pytest.approx(K_TRUE, rel=0.25)
    np.testing.assert_allclose(at.k_rgb, at.k, rtol=0.05)
    off = sf.fit_sun(x, n, L, vis, CFG, direction=_unit(np.array([-0.7, 0.3, 0.4])))
    assert not off.usable and "z =" in off.reason        # no shadow toward a wrong sun


def test_rescale_seen_sun_sets_its_irradiance_per_channel():
    from comgs_dr.core.equirect import equirect_directions, solid_angle_image
    h, w = 128, 256
    dirs = equirect_directions(h, w)
    sky = np.where(dirs[..., 2:3] > 0, [0.4, 0.5, 0.7], 0.1).astype(np.float64)
    pano = sky.copy()
    cosd = dirs @ SUN
    pano[cosd > np.cos(np.radians(3))] = [60.0, 60.0, 70.0]          # a clipped, bluish sun
    observed = np.ones((h, w), bool)
    d = sf.seen_sun(pano, observed, _unit(SUN + [0.1, -0.1, -0.2]))
    assert np.degrees(np.arccos(np.clip(d @ SUN, -1, 1))) < 1.0
    assert sf.seen_sun(sky, observed, SUN) is None                    # nothing hot there
    k = np.array([3.0, 2.2, 1.2])
    fit = sf.SunFit(d, float(k @ sf.LUMA), k, 20.0, 0.0, 0.1, True, "", 100, 0.0)
    out, what = sf.rescale_seen_sun(pano, fit)
    assert what.startswith("rescaled")
    disk = (dirs @ d) >= np.cos(np.radians(8.0))
    rest = out.astype(np.float64).copy()
    rest[disk] = np.median(out[((dirs @ d) >= np.cos(np.radians(12.0))) & ~disk], 0)
    e_sun = np.einsum("hwc,hw->c", out - rest, np.maximum(dirs @ d, 0) * solid_angle_image(h, w))
    np.testing.assert_allclose(e_sun / sf.up_irradiance(rest), k, rtol=1e-3)
    np.testing.assert_array_equal(out[~disk], pano[~disk].astype(np.float32))


def test_estimate_light_rescales_a_clipped_seen_sun_and_keeps_a_measured_one():
    from comgs_dr.core.equirect import equirect_directions
    from comgs_dr.stages.estimate_light import _seen_sun
    sc, p = _scene(True)
    receivers = sf.scene_receivers(sc, p, "srgb", CFG)
    h, w = 64, 128
    dirs = equirect_directions(h, w)
    pano = np.where(dirs[..., 2:3] > 0, [0.4, 0.5, 0.7], 0.1) * np.ones(3)
    sun = (dirs @ SUN) > np.cos(np.radians(4))
    pano[sun] = 50.0
    ldr = np.clip(pano / 4.0, 0.0, 1.0)                      # the sun clips at EV 0
    out, rec, what = _seen_sun(pano, receivers, SUN, ldr)
    assert what.startswith("rescaled") and rec["usable"]
    assert not np.array_equal(out, pano)
    kept, rec, what = _seen_sun(pano, receivers, SUN, ldr * 0.5)  # below white: measured
    assert kept is pano and rec is None and "not clipped" in what


def _walled_scene(sun, seed=2, k=K_TRUE):
    """A 3×3 ground, a 0.8-high wall along x at y = 1 and a block in front of it, under
    ``sun`` with outward normals (the block's shadow ends on the wall, then climbs it)."""
    boxes = (((-1.5, 1.0, 0.0), (1.5, 1.15, 0.8)), ((-0.2, 0.2, 0.0), (0.2, 0.5, 0.5)))
    return _surfel_scene(boxes, sun, k, 12000, seed, 0.25, True)


def test_a_shadow_climbing_a_wall_fixes_the_low_suns_elevation():
    """A low sun (12°): the block's short ground shadow ends on the wall behind it, then
    climbs the wall. The wall's receivers find the sun (measured 7.2° off, elevation 18°
    for 12°: the traced shadow of wide surfels is taller than the true one); the ground's
    receivers alone find no usable shadow (z −0.8)."""
    el, az = np.radians(12.0), np.radians(-100.0)
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    sc, p = _walled_scene(sun)
    x, n, L, vis = sf.scene_receivers(sc, p, "srgb", CFG)
    assert (n[:, 2] < 0.5).sum() > 100                       # the wall's receivers are in
    fit = sf.fit_sun(x, n, L, vis, CFG)
    assert fit.usable, fit.reason
    assert np.degrees(np.arccos(np.clip(fit.direction @ sun, -1, 1))) < 10.0
    g = n[:, 2] > 0.9
    ground = sf.fit_sun(x[g], n[g], L[g], lambda d: vis(d)[g], CFG)
    assert not ground.usable or np.degrees(np.arccos(np.clip(ground.direction @ sun, -1, 1))) > 20
    sc, p = _walled_scene(sun, k=0.0)                 # overcast: walls and their own shading,
    none = sf.fit_sun_in_scene(sc, p, "srgb", CFG)     # no shadow: nothing invented
    assert not none.usable and "no usable cast shadow" in none.reason, none.reason


def test_turbidity_from_the_shadows_sun_sky_ratio():
    """A hazier model sky takes light from its sun (k falls with turbidity at any elevation);
    the turbidity read back from a model's own k is that turbidity; out of range: clamped."""
    from comgs_dr.lighting import clear_sky
    for el in (10.0, 45.0):
        d = np.array([np.cos(np.radians(el)), 0.0, np.sin(np.radians(el))])
        ks = [clear_sky.sun_sky_ratio(d, t) for t in (2.0, 5.0, 8.0)]
        assert ks[0] > ks[1] > ks[2] > 0
        for t, k in zip((2.0, 5.0, 8.0), ks):
            assert clear_sky.turbidity_for(d, k) == pytest.approx(t, abs=0.05)
        assert clear_sky.turbidity_for(d, 1e3) == 1.5
        assert clear_sky.turbidity_for(d, 1e-3) == 10.0 == clear_sky.turbidity_for(d, np.nan)


def test_an_unseen_sky_too_dim_for_the_ground_it_lights_is_raised():
    """A ground reflecting more than it receives (E_down / E_up > 1) is impossible: the
    unseen sky (and the sun that scales with it) is raised until the brightest channel
    reflects max_albedo; a plausible one is left alone; seen pixels never change."""
    from comgs_dr.core.equirect import equirect_directions, solid_angle_image
    from comgs_dr.lighting import clear_sky
    h, w = 32, 64
    dirs = equirect_directions(h, w)
    rad = np.where(dirs[..., 2:3] > 0, [0.1, 0.1, 0.12], [0.3, 0.2, 0.1])
    unseen = (dirs[..., 2] > 0.2)                              # a band above the horizon seen
    k, el = np.array([2.0, 1.5, 1.0]), np.radians(30.0)
    out, s, implied = clear_sky.ground_albedo_floor(rad, unseen, k, el, 0.5)
    assert implied[0] > 1.0 and s > 1.0
    np.testing.assert_array_equal(out[~unseen], rad[~unseen])
    np.testing.assert_allclose(out[unseen], s * rad[unseen])
    sa = solid_angle_image(h, w)
    e_up = np.einsum("hwc,hw->c", out, sa * np.maximum(dirs[..., 2], 0))
    e_down = np.einsum("hwc,hw->c", out, sa * np.maximum(-dirs[..., 2], 0))
    ratio = e_down / (e_up * (1 + k * np.sin(el)))
    assert ratio.max() == pytest.approx(0.5, rel=1e-6)           # the brightest channel at 0.5
    same, s1, _ = clear_sky.ground_albedo_floor(out, unseen, k, el, 0.5)
    assert s1 == 1.0 and (same == out).all()                   # plausible now: left alone
    off, s0, _ = clear_sky.ground_albedo_floor(rad, unseen, k, el, 0.0)
    assert s0 == 1.0 and (off == rad).all()


def test_the_sky_lift_is_capped_when_little_of_it_is_unseen():
    """A small unseen patch under a bright ground would need a huge factor; it gets at
    most MAX_LIFT (not a bright light nobody saw)."""
    from comgs_dr.core.equirect import equirect_directions
    from comgs_dr.lighting import clear_sky
    h, w = 32, 64
    dirs = equirect_directions(h, w)
    rad = np.where(dirs[..., 2:3] > 0, 0.1, 0.5) * np.ones(3)
    patch = dirs[..., 2] > 0.97                                   # a few pixels at the zenith
    out, s, implied = clear_sky.ground_albedo_floor(rad, patch, np.zeros(3), 0.5, 0.5)
    assert implied.max() > 2.0 and s == clear_sky.MAX_LIFT
    np.testing.assert_allclose(out[patch], clear_sky.MAX_LIFT * rad[patch])


def test_without_a_sun_the_unseen_sky_is_lifted_to_the_default_ceiling():
    """No sun from the shadows (too low, overcast): the completion's unseen sky alone is
    raised until E_down / E_up of the brightest channel is MAX_GROUND_ALBEDO; the observed
    mask may come at the trace's resolution (resized nearest); seen pixels never change."""
    from comgs_dr.core.equirect import equirect_directions, solid_angle_image
    from comgs_dr.lighting import clear_sky
    h, w = 32, 64
    dirs = equirect_directions(h, w)
    rad = np.where(dirs[..., 2:3] > 0, [0.1, 0.1, 0.12], [0.06, 0.045, 0.03])
    observed = np.repeat(np.repeat(dirs[..., 2] < 0.3, 2, 0), 2, 1)        # [64, 128]
    out, s, implied = clear_sky.lift_unseen_sky(rad, observed)
    seen = dirs[..., 2] < 0.3
    assert s > 1.0 and implied.max() > clear_sky.MAX_GROUND_ALBEDO
    np.testing.assert_array_equal(out[seen], rad[seen])
    np.testing.assert_allclose(out[~seen], s * rad[~seen])
    sa = solid_angle_image(h, w)
    e_up = np.einsum("hwc,hw->c", out, sa * np.maximum(dirs[..., 2], 0))
    e_down = np.einsum("hwc,hw->c", out, sa * np.maximum(-dirs[..., 2], 0))
    assert (e_down / e_up).max() == pytest.approx(clear_sky.MAX_GROUND_ALBEDO, rel=1e-6)
    dim = np.where(dirs[..., 2:3] > 0, 1.0, 0.1) * np.ones(3)            # ground reflects 0.1
    same, s1, _ = clear_sky.lift_unseen_sky(dim, observed)
    assert s1 == 1.0 and (same == dim).all()


def test_a_rival_is_scored_without_the_best_shadows_receivers():
    """A direction whose long shadow takes in a quarter of the true shadow borrows its
    darkening (raw z well above 0); scored without the true shadow's receivers, as
    ``_Fitter.rival`` does, it keeps only its own (here: none, noise)."""
    from comgs_dr.lighting import sun_fit as S
    rng = np.random.default_rng(0)
    g = np.linspace(0.0, 1.0, 40)
    x = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    x = np.concatenate([x, np.zeros((len(x), 1))], 1)
    n = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    r = np.linalg.norm(x[:, :2] - 0.5, axis=1)
    disc = r < 0.12                                                  # the true shadow
    corner = (x[:, 0] < 0.15) & (x[:, 1] < 0.15)                     # the rival's own shadow:
    band = ((r > 0.095) & disc & (x[:, 0] > 0.5)) | corner           # nothing darker there, and
                                                                     # the true one's rim
    L = np.exp(rng.normal(0.0, 0.1, len(x)))[:, None] * np.where(disc, 0.6, 1.0)[:, None]
    L = np.repeat(L, 3, 1)
    true_d, rival_d = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.6, 0.8])
    vis = {tuple(np.round(true_d, 6)): np.where(disc, 0.0, 1.0),
           tuple(np.round(rival_d, 6)): np.where(band, 0.0, 1.0)}
    f = S._Fitter(x, n, L, lambda d: vis[tuple(np.round(d, 6))], S.SunFitConfig())
    z, V = f.score(true_d)
    zr_raw, Vr = f.score(rival_d)
    assert S._overlap(Vr < 0.5, V < 0.5) < S.RIVAL_OVERLAP
    assert zr_raw >= 3.0 and z > zr_raw
    # a best sun only just strong enough for the raw rival (rivals below half the needed z
    # are not scored): without the borrowed receivers the rival keeps only its corner's
    # noise (raw 4.8 -> 2.4 here), and the best sun passes the rival test
    assert f.rival(S.RIVAL_RATIO * zr_raw, V) < 0.6 * zr_raw
