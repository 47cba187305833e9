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


def test_estimate_light_uses_the_background(trained):
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
    with pytest.raises(FileNotFoundError, match="no such folder"):
        estimate_light(run / "point_cloud.ply", pos,
                       EstimateConfig(background=str(run / "nowhere"), **cfg), FillBackend("mean"))


def test_bad_background_settings():
    with pytest.raises(ValueError, match="background must be"):
        RadianceConfig(background="sky")
    with pytest.raises(ValueError, match="env_resolution"):
        RadianceConfig(env_resolution=2)


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
                     "--ground-half", "6", "--quiet"])
    assert code == 0
    comp = json.loads((tmp_path / "d" / "composition.json").read_text())
    assert comp["scene"]["n_train"] == 5 and comp["scene"]["sky_views"] == 2
    assert comp["scene"]["shapes"]["ground"]["half_size"] == 6.0
