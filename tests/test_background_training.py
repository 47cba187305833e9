"""Step 1 with a learned sky behind the surfels (``RadianceConfig(background="env")``,
``comgs_dr.train.background``) and its use by the lighting estimation.

One tiny composition dataset (24 px) under a procedural sky with a low sun, with capture
views that look out over the horizon, is rendered once per module.
"""
import json

import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.data import composition_dataset as cd
from comgs_dr.data import procedural
from comgs_dr.data.load import load_dataset
from comgs_dr.lighting.backends import FillBackend
from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light
from comgs_dr.stages.reconstruct import CKPT_FORMAT, RadianceConfig, train_radiance
from comgs_dr.train import background as bgenv
from comgs_dr.train import checkpoint as ck

SKY_VIEWS = 4


@pytest.fixture(scope="module")
def sky_scene(tmp_path_factory, variant):
    out = tmp_path_factory.mktemp("sky")
    sky = procedural.procedural_sky(out / "sky.exr", sun_elevation_deg=15.0)
    studio = procedural.procedural_studio(out / "studio.exr")        # no shared data needed
    mesh = procedural.procedural_object_yup(out / "torus.ply")
    cd.make_composition_dataset(cd.CompositionDatasetConfig(
        out_dir=out / "ds", objects=(str(mesh),), scene_map=sky, object_map=studio,
        resolution=24, scene_views=6,
        sky_views=SKY_VIEWS, object_views=1, test_views=2, spp=4, sfm_points=400),
        progress=False)
    return out / "ds"


def _cfg(**kw):
    return RadianceConfig.from_preset("scene", **{**dict(
        iterations=80, eval_every=40, eval_views=2, log_every=20, checkpoint_every=40,
        max_hits=16, sh_degree=0, background="env", env_resolution=16, lr_env=0.05), **kw})


@pytest.fixture(scope="module")
def trained(sky_scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("run")
    s = train_radiance(load_dataset(sky_scene / "scene"), run, _cfg(), progress=False)
    return run, s


def test_sky_cameras_look_out_over_the_horizon(sky_scene):
    frames = json.loads((sky_scene / "scene" / "transforms_train.json").read_text())["frames"]
    sky = frames[-SKY_VIEWS:]
    for f in sky:
        m = np.asarray(f["transform_matrix"])              # OpenGL: the camera looks along -Z
        fwd, pos = -m[:3, 2], m[:3, 3]
        pitch = np.degrees(np.arcsin(fwd[2]))
        assert 4.9 < pitch < 30.1
        assert np.dot(fwd[:2], pos[:2]) > 0                # outwards, away from the scene
    comp = json.loads((sky_scene / "composition.json").read_text())
    assert comp["scene"]["sky_views"] == SKY_VIEWS


def test_background_files_and_the_sky_is_learned(sky_scene, trained):
    run, s = trained
    assert np.isfinite(s["psnr_test"])
    rad, obs = bgenv.load(run)
    assert rad.shape == (16, 16, 3) and obs.shape == (16, 16)
    assert np.isfinite(rad).all() and rad.min() >= 0
    # the sky views saw the upper hemisphere: observed texels above the horizon exist
    from comgs_dr.core.octahedral import texel_directions_np
    up = texel_directions_np(16).reshape(16, 16, 3)[..., 2] > 0.15
    assert (obs[up] > 0.9).sum() >= 4
    # where the surfels leave the sky view open, the render (= the background) matches the
    # captured sky much better than the initial mean colour does
    from comgs_dr.surfels import load_ply
    from comgs_dr.surfels.scene import gbuffer_scene
    from comgs_dr.emitters.octenvmap import emitter_class
    data = load_dataset(sky_scene / "scene")
    p = load_ply(run / "point_cloud.ply")
    err, err0 = [], []
    mean = np.mean([v.image.reshape(-1, 3).mean(0) for v in data.train], 0)
    for v in data.train[-SKY_VIEWS:]:
        sc = gbuffer_scene(p, v.camera.sensor_dict(), max_hits=16, targets="color,weight",
                           environment=emitter_class().from_radiance(rad), env_background=True)
        img = np.array(mi.render(sc))
        open_ = img[..., 3] < 0.05
        err += list(np.abs(img[..., :3] - v.image)[open_].ravel())
        err0 += list(np.abs(mean - v.image)[open_].ravel())
    assert len(err) > 30
    assert np.mean(err) < 0.5 * np.mean(err0), (np.mean(err), np.mean(err0))


def test_checkpoint_carries_the_background(sky_scene, tmp_path):
    data = load_dataset(sky_scene / "scene")
    run = tmp_path / "run"
    train_radiance(data, run, _cfg(iterations=40), progress=False)
    arrays, moments, state = ck.load_checkpoint(run / ck.CKPT_NAME, CKPT_FORMAT)
    assert arrays["env"].shape == (16, 16, 3)          # (its Adam moments restart on resume)
    # resumes with a 10x smaller step: 20 restarted Adam steps move a texel by <= ~20 lr each
    # (0.1 here), so a resume from the initial map would show as the whole learnt change
    s = train_radiance(data, run, _cfg(iterations=60, lr_env=0.005), progress=False)
    assert s["iterations"] == 60
    arrays2, _, _ = ck.load_checkpoint(run / ck.CKPT_NAME, CKPT_FORMAT)
    assert not np.array_equal(arrays2["env"], arrays["env"])               # kept learning
    env0 = np.mean([v.image[..., :3].reshape(-1, 3).mean(0) for v in data.train], 0)
    learnt = np.abs(arrays["env"] - env0).mean()                           # first 40 steps
    moved = np.abs(arrays2["env"] - arrays["env"]).mean()                  # the resumed 20
    assert moved < 0.5 * learnt, (moved, learnt)                           # from where it was


def test_estimate_light_uses_the_background(trained, monkeypatch, caplog, tmp_path):
    run, _ = trained
    pos = [0.0, 0.0, 0.3]
    cfg = dict(width=64, height=32, oct_res=16, light_head="none")
    with_bg = estimate_light(run / "point_cloud.ply", pos, EstimateConfig(**cfg), FillBackend("mean"))
    without = estimate_light(run / "point_cloud.ply", pos, EstimateConfig(background="none", **cfg),
                             FillBackend("mean"))
    assert with_bg["meta"]["trace"]["background"] == str(run)
    assert with_bg["coverage"] > without["coverage"] + 0.05
    m = with_bg["input"]["mask"]
    sky = slice(9, 15)                                 # 6..39 degrees above the horizon
    assert m[sky].mean() > without["input"]["mask"][sky].mean() + 0.2
    # the open sky (the background's share) is part of what is seen above the horizon
    mw = with_bg["meta"]
    assert without["meta"]["open_sky_fraction"] is None
    assert 0.05 < mw["open_sky_fraction"] <= mw["seen_sky_fraction"] + 1e-9
    from comgs_dr.stages.estimate_light_files import sky_text
    assert f"(open sky {100 * mw['open_sky_fraction']:.1f}%)" in sky_text(mw)
    # little open sky in a well-seen upper hemisphere: warned (the threshold moved above it)
    from comgs_dr.lighting import hdr
    for limit, warned in ((mw["open_sky_fraction"] + 0.01, True), (0.0, False)):
        monkeypatch.setattr(hdr, "OPEN_SKY_WARN", limit)
        caplog.clear()
        with caplog.at_level("WARNING", logger="comgs_dr.stages.estimate_light"):
            estimate_light(run / "point_cloud.ply", pos, EstimateConfig(**cfg), FillBackend("mean"))
        assert ("is open sky" in caplog.text) == warned
    # another run's background, given by hand: used, and said to be another scene's sky
    import shutil

    from comgs_dr.train.run import write_run_info
    mine, other = tmp_path / "mine", tmp_path / "other"
    for d, capture in ((mine, "capture"), (other, "another_capture")):
        shutil.copytree(run, d)
        write_run_info(d, tmp_path / capture, "scene", 1, False)
    monkeypatch.setattr(hdr, "OPEN_SKY_WARN", 0.0)
    for bg, warned in ((str(other), True), (str(mine), False)):
        caplog.clear()
        with caplog.at_level("WARNING", logger="comgs_dr.stages.estimate_light"):
            estimate_light(mine / "point_cloud.ply", pos, EstimateConfig(background=bg, **cfg),
                           FillBackend("mean"))
        assert ("its sky is another scene's" in caplog.text) == warned, bg
    with pytest.raises(FileNotFoundError, match="no such folder"):
        estimate_light(run / "point_cloud.ply", pos,
                       EstimateConfig(background=str(run / "nowhere"), **cfg), FillBackend("mean"))


def test_bad_background_settings():
    with pytest.raises(ValueError, match="background must be"):
        RadianceConfig(background="sky")
    with pytest.raises(ValueError, match="env_resolution"):
        RadianceConfig(env_resolution=2)
    with pytest.raises(ValueError, match="lr_env_final must be > 0"):
        RadianceConfig(lr_env_final=0.0)


def test_env_learning_rate_decays_exponentially():
    """lr_env at the start, lr_env_final at the end, geometric in between (the sky's Adam
    steps set the texels' noise floor: a constant step leaves them speckled)."""
    from types import SimpleNamespace

    from comgs_dr.stages.reconstruct import Trainer
    cfg = RadianceConfig(lr_env=0.01, lr_env_final=0.0001)
    lr = [Trainer._lr_env(SimpleNamespace(cfg=cfg, run_fraction=lambda t=t: t))
          for t in (0.0, 0.5, 1.0)]
    assert lr == pytest.approx([0.01, 0.001, 0.0001])
    const = RadianceConfig(lr_env=0.05)                 # None: constant, whatever lr_env
    assert Trainer._lr_env(SimpleNamespace(cfg=const, run_fraction=lambda: 1.0)) == 0.05


def test_render_run_shows_the_learned_sky(sky_scene, trained):
    """``comgs render`` of an env-background run renders the sky (its PSNR is the trainer's)
    and keeps the EXR colour layer surfels-only (the sky removed)."""
    from comgs_dr.core import exr
    from comgs_dr.stages.render_run import render_run
    from comgs_dr.train.run import write_run_info
    run, s = trained
    write_run_info(run, sky_scene / "scene", "scene", 1, False)
    r = render_run(run, "test", progress=False, max_hits=16)
    assert abs(r["psnr"] - s["psnr_test"]) < 0.5, (r["psnr"], s["psnr_test"])
    layers = exr.read_layers(run / "render_test" / "000.exr")
    rgba = np.asarray(layers[""] if "" in layers else next(iter(layers.values())))
    assert np.isfinite(rgba).all()
    a = rgba[..., 3]
    assert np.all(rgba[..., :3][a < 1e-4] == 0)                   # no sky in the surfel layer


def test_cli_make_dataset_with_sky_views(sky_scene, tmp_path):
    from comgs_dr import cli
    src = sky_scene.parent
    code = cli.main(["make-dataset", "composition", "--out", str(tmp_path / "d"), "--objects",
                     str(src / "torus.ply"), "--scene-map", str(src / "sky.exr"), "--object-map",
                     str(src / "studio.exr"), "--res", "16", "--scene-views", "3",
                     "--object-views", "2", "--test-views", "1", "--sky-views", "2",
                     "--ground-half", "6", "--probe-height", "0", "--quiet"])
    assert code == 0
    assert not (tmp_path / "d" / "probes").exists()          # 0: no probes
    comp = json.loads((tmp_path / "d" / "composition.json").read_text())
    assert comp["scene"]["n_train"] == 5 and comp["scene"]["sky_views"] == 2
    assert comp["scene"]["shapes"]["ground"]["half_size"] == 6.0


def test_sky_cameras_aim_at_the_sun():
    """``aim_deg``: the first view looks along the given azimuth, its pitch clamped to the
    range; the others keep stratified azimuths."""
    for aim, pitch in (((123.0, 12.0), 12.0), ((-40.0, 60.0), 30.0)):
        cams = cd.sky_cameras(6, 10.0, np.random.default_rng(1), (5.0, 30.0), aim_deg=aim)
        m = np.asarray(cams[0]["transform_matrix"])
        fwd = -m[:3, 2]
        assert abs(np.degrees(np.arcsin(fwd[2])) - pitch) < 1e-6
        az = np.degrees(np.arctan2(fwd[1], fwd[0]))
        assert abs((az - aim[0] + 180.0) % 360.0 - 180.0) < 1e-6
        gaps = np.diff(sorted(c["azimuth_deg"] for c in cams))
        assert gaps.max() < 2 * 360.0 / 6 + 1e-6                   # still sweeps around


def test_capture_maps_record_clipped_rays(sky_scene, trained):
    """A pixel clipped in red and blue, seen through the open sky, is recorded with its ray
    direction, those channels, its T_final and its pixel radius; nothing else is. The
    observed map is ``observed_fraction``'s."""
    from comgs_dr.core.cameras import camera_rays
    from comgs_dr.emitters.octenvmap import emitter_class
    from comgs_dr.surfels import load_ply
    from comgs_dr.surfels.scene import gbuffer_scene
    run, _ = trained
    data = load_dataset(sky_scene / "scene")
    p = load_ply(run / "point_cloud.ply")
    rad, _ = bgenv.load(run)
    v = data.train[-1]
    sc = gbuffer_scene(p, v.camera.sensor_dict(), max_hits=16, targets="color,weight",
                       environment=emitter_class().from_radiance(rad), env_background=True)
    integ = sc.integrator()
    T = 1.0 - np.asarray(integ.split(mi.render(sc))["weight"]).reshape(-1)
    k = int(np.argmax(T))
    assert T[k] > 0.5
    img = np.zeros((v.camera.height * v.camera.width, 3))
    img[k] = [1.0, 0.5, 0.99]
    obs, rec = bgenv.capture_maps(sc, integ, [0], 16, [img.reshape(v.image.shape)])
    assert np.array_equal(obs, bgenv.observed_fraction(sc, integ, [0], 16))
    d = np.asarray(camera_rays(sc.sensors()[0])[0]).reshape(-1, 3)[k]
    assert len(rec["directions"]) == 1
    assert np.allclose(rec["directions"][0], d, atol=1e-6)
    assert rec["channels"][0].tolist() == [1, 0, 1]
    assert np.isclose(rec["weight"][0], T[k], atol=1e-6)
    fov = np.radians(v.camera.fov_x_deg) / v.camera.width        # about one pixel's angle
    assert 0.3 * fov < rec["radius"][0] < 0.8 * fov
    _, none = bgenv.capture_maps(sc, integ, [0], 16, [np.zeros(v.image.shape)])
    assert len(none["directions"]) == 0
    with pytest.raises(ValueError, match="pixels"):
        bgenv.capture_maps(sc, integ, [0], 16, [np.zeros((3, 3, 3))])
    # transparent pixels show no sky: alpha 0 everywhere -> nothing observed, nothing recorded
    hw = v.image.shape[:2]
    clear, rec0 = bgenv.capture_maps(sc, integ, [0], 16, [img.reshape(v.image.shape)],
                                     masks=[np.zeros(hw)])
    assert clear.max() == 0.0 and len(rec0["directions"]) == 0
    half, _ = bgenv.capture_maps(sc, integ, [0], 16, masks=[np.full(hw, 0.5)])
    np.testing.assert_allclose(half, 0.5 * obs)
    same, _ = bgenv.capture_maps(sc, integ, [0], 16, masks=[None])
    assert np.array_equal(same, obs)
    with pytest.raises(ValueError, match="mask 0"):
        bgenv.capture_maps(sc, integ, [0], 16, masks=[np.zeros((3, 3))])


def test_transparent_fraction():
    """The share of training pixels with alpha < ½ (reconstruct warns on it with env)."""
    from comgs_dr.stages.reconstruct import transparent_fraction
    from types import SimpleNamespace as NS
    img = np.zeros((4, 5, 3))
    a = np.ones((4, 5))
    a[:2] = 0.0                                                      # 10 of 20 pixels clear
    a[2, 0] = 0.5                                                    # half covered: not clear
    views = [NS(image=img, mask=a), NS(image=img, mask=None)]
    assert transparent_fraction(views) == pytest.approx(10 / 40)
    assert transparent_fraction([NS(image=img, mask=None)]) == 0.0


def test_pixel_radius_is_the_equal_area_disc():
    """A uniform angular grid of step a gives r = a/sqrt(pi) (area pi r^2 = a^2)."""
    a = np.radians(0.5)
    th, ph = np.meshgrid(np.arange(5) * a, np.pi / 2 + np.arange(4) * a)
    d = np.stack([np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), np.cos(ph)], -1)
    np.testing.assert_allclose(bgenv.pixel_radius(d), a / np.sqrt(np.pi), rtol=0.02)


def _record(dirs, channels, radius=np.radians(0.6), weight=1.0):
    dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    m = len(dirs)
    return {"directions": dirs, "channels": np.asarray(channels).reshape(m, 3),
            "weight": np.full(m, weight), "radius": np.full(m, radius)}


def test_splat_record_covers_each_rays_disc():
    """A ray's disc covers the panorama pixels within its radius, weighted by T per
    channel; a radius smaller than the panorama's pixels still marks the ray's pixel."""
    from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles
    h, w = 128, 256
    d = np.array([0.6, 0.3, 0.5])
    d /= np.linalg.norm(d)
    out = bgenv.splat_record(_record(d, [1, 1, 0], radius=np.radians(5.0), weight=0.8), h, w)
    ang = np.degrees(np.arccos(np.clip(equirect_directions(h, w) @ d, -1, 1)))
    on = out[..., 0] > 0
    assert np.all(ang[on] <= 5.0 + 1.5)                     # + the ray's own pixel
    assert np.all(on[ang < 5.0])
    assert np.allclose(out[on][:, :2], 0.8) and out[..., 2].max() == 0
    area = (pixel_solid_angles(h, w) * np.ones((h, w)))[on].sum()
    assert abs(area / (np.pi * np.radians(5.0) ** 2) - 1) < 0.15
    tiny = bgenv.splat_record(_record(d, [1, 1, 1], radius=1e-4), h, w)
    assert (tiny.max(-1) > 0).sum() == 1
    empty = bgenv.splat_record(_record(np.zeros((0, 3)), np.zeros((0, 3))), h, w)
    assert empty.shape == (h, w, 3) and empty.max() == 0


def test_clipped_record_round_trip_and_old_runs(tmp_path):
    rad = np.full((8, 8, 3), 0.5)
    bgenv.save(tmp_path, rad, np.ones((8, 8)))
    assert bgenv.load_clipped(tmp_path) is None                    # a run from before
    rec = _record([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], [[1, 0, 0], [1, 1, 1]])
    bgenv.save(tmp_path, rad, np.ones((8, 8)), rec)
    back = bgenv.load_clipped(tmp_path)
    for k in rec:
        np.testing.assert_allclose(back[k], rec[k], atol=1e-6)
    bad = dict(rec, weight=np.array([np.nan, 1.0]))
    with pytest.raises(ValueError, match="non-finite"):
        bgenv.save(tmp_path, rad, np.ones((8, 8)), bad)
    with pytest.raises(ValueError, match="differ in length"):
        bgenv.save(tmp_path, rad, np.ones((8, 8)), dict(rec, radius=np.ones(3) * 0.01))
    with pytest.raises(ValueError, match="unit"):
        bgenv.save(tmp_path, rad, np.ones((8, 8)), dict(rec, directions=rec["directions"] * 2))
    with pytest.raises(ValueError, match="needs directions"):
        bgenv.save(tmp_path, rad, np.ones((8, 8)), {"directions": rec["directions"]})
    np.savez(tmp_path / bgenv.CLIPPED_FILE, **dict(rec, radius=np.array([0.01, -1.0])))
    with pytest.raises(ValueError, match="radii"):
        bgenv.load_clipped(tmp_path)


def test_step1_writes_the_clipped_record_and_estimate_light_uses_it(trained, tmp_path):
    """The trained run has a clipped record; a recorded ray turns into a white, observed
    region of the placement's panorama that the light head sees, in its direction."""
    import shutil
    run, _ = trained
    rec = bgenv.load_clipped(run)
    assert rec is not None and rec["directions"].shape[1] == 3
    run2 = tmp_path / "run"
    shutil.copytree(run, run2)
    rad, obs = bgenv.load(run2)
    from comgs_dr.core.octahedral import texel_directions_np
    dirs = texel_directions_np(16).reshape(16, 16, 3)
    up = (dirs[..., 2] > 0.3) & (obs > 0.9)
    assert up.any()
    j, i = np.argwhere(up)[0]
    rad = np.minimum(rad, 0.8)                                     # nothing white on its own
    bgenv.save(run2, rad, obs, _record(dirs[j, i], [1, 1, 1], radius=np.radians(2.0)))
    pos = [0.0, 0.0, 0.3]
    cfg = EstimateConfig(width=128, height=64, oct_res=16, light_head="none")
    r = estimate_light(run2 / "point_cloud.ply", pos, cfg, FillBackend("mean"))
    assert r["meta"]["trace"]["background_clipped"] > 0
    assert r["meta"]["light_head_block"] == 1                      # no head run here
    from comgs_dr.lighting import lights
    regs = lights.clipped_regions(r["input"]["rgb"], r["input"]["mask"])
    assert regs, "the recorded ray is not a clipped region of the panorama"
    assert np.degrees(np.arccos(np.clip(regs[0].direction @ dirs[j, i], -1, 1))) < 5
    bgenv.save(run2, rad, obs, _record(np.zeros((0, 3)), np.zeros((0, 3))))
    r0 = estimate_light(run2 / "point_cloud.ply", pos, cfg, FillBackend("mean"))
    assert not lights.clipped_regions(r0["input"]["rgb"], r0["input"]["mask"])
    # a record part wider than clipped_max_texels is not applied
    big = _record(dirs[j, i], [1, 1, 1], radius=np.radians(40.0))
    bgenv.save(run2, rad, obs, big)
    r1 = estimate_light(run2 / "point_cloud.ply", pos, EstimateConfig(
        width=128, height=64, oct_res=16, light_head="none", clipped_max_texels=16),
        FillBackend("mean"))
    assert r1["meta"]["trace"]["background_clipped"] == 0
    r2 = estimate_light(run2 / "point_cloud.ply", pos, cfg, FillBackend("mean"))   # inf
    assert r2["meta"]["trace"]["background_clipped"] > 100
    # with the shipped head: a record coarser than the panorama's pixels (4° discs, 2.8°
    # pixels) makes the head read 2x2 blocks, and its light lands on the recorded ray
    bgenv.save(run2, rad, obs, _record(dirs[j, i], [1, 1, 1], radius=np.radians(4.0)))
    r3 = estimate_light(run2 / "point_cloud.ply", pos, EstimateConfig(
        width=128, height=64, oct_res=16), FillBackend("mean"))
    assert r3["meta"]["light_head_block"] == 2
    assert r3["lobes"], "no light from the recorded clipped ray"
    d3 = np.asarray(r3["lobes"][0]["direction"])
    assert np.degrees(np.arccos(np.clip(d3 @ dirs[j, i], -1, 1))) < 8


def test_clipped_level_is_the_light_heads():
    """Step 1 records a pixel as clipped at the level at which the light head reads one."""
    from comgs_dr.lighting import lights
    assert bgenv.CLIPPED == lights.SAT


def test_step1_weighs_the_sky_by_alpha_unless_masks_are_given(sky_scene, tmp_path, monkeypatch,
                                                              caplog):
    """train_radiance hands the views' alpha to capture_maps (and warns on transparent
    pixels); a dataset whose masks came from a masks folder (``meta["masks"]``, e.g. COLMAP
    feature masks) is not read as alpha."""
    import logging
    seen = []
    real = bgenv.capture_maps

    def spy(*a, masks=None, **kw):
        seen.append(masks)
        return real(*a, masks=masks, **kw)

    monkeypatch.setattr(bgenv, "capture_maps", spy)
    data = load_dataset(sky_scene / "scene")
    for v in data.train:                                     # the upper half transparent
        v.mask = np.ones(v.image.shape[:2], np.float32)
        v.mask[: v.mask.shape[0] // 2] = 0.0
    cfg = _cfg(iterations=4, eval_every=4, log_every=4, checkpoint_every=4)
    with caplog.at_level(logging.WARNING, logger="comgs_dr.stages.reconstruct"):
        train_radiance(data, tmp_path / "a", cfg, progress=False)
    assert "transparent pixels" in caplog.text
    assert len(seen[-1]) == len(data.train)
    assert all(m is v.mask for m, v in zip(seen[-1], data.train))
    caplog.clear()
    data.meta = {**(data.meta or {}), "masks": "feature_masks"}
    with caplog.at_level(logging.WARNING, logger="comgs_dr.stages.reconstruct"):
        train_radiance(data, tmp_path / "b", cfg, progress=False)
    assert seen[-1] is None and "transparent pixels" not in caplog.text


def test_background_auto_is_decided_from_the_data(sky_scene, trained):
    """``background='auto'`` (the default): opaque scene photos learn the far field, an
    object cut out by its alpha keeps the grey level; the run reports the choice."""
    from comgs_dr.stages.reconstruct import resolve_background
    scene = load_dataset(sky_scene / "scene")
    assert RadianceConfig().background == "auto"
    cfg, why = resolve_background(RadianceConfig.from_preset("scene"), scene)
    assert cfg.background == "env" and why.startswith("env: scene preset")
    cfg, why = resolve_background(RadianceConfig.from_preset("scene", background="grey"), scene)
    assert cfg.background == "grey" and "given" in why
    import dataclasses
    views = [dataclasses.replace(v, mask=np.zeros(v.image.shape[:2], np.float32))
             for v in scene.train]                      # the same photos, all transparent
    cut = dataclasses.replace(scene, train=views)
    cfg, why = resolve_background(RadianceConfig.from_preset("scene"), cut)
    assert cfg.background == "grey" and "100.0% transparent" in why
    run, summary = trained
    assert summary["background"] == "env (given)"
