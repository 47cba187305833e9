"""Exposure and white balance between the object's and the scene's captures
(``data.exposure``, ``comgs compose --white-patch/--exposure-gain/--grey-world``): photos
linearised from sRGB, the gain estimated from a reference seen in both, given, or assumed 1
and said so; compose multiplies the object's albedo by it and records it."""
import json

import mitsuba as mi
import numpy as np
import pytest
from PIL import Image

from comgs_dr import cli
from comgs_dr.core.colorspace import LUMA, srgb_decode, srgb_encode
from comgs_dr.data import exposure as X

# the object capture: exposure x2 and a warm white balance; the scene capture: neutral, x0.9
K_OBJECT = 2.0 * np.array([1.25, 1.0, 0.75])
K_SCENE = 0.9 * np.array([1.0, 1.0, 1.0])
TRUE_GAIN = K_SCENE / K_OBJECT                       # (0.36, 0.45, 0.6)
TOLERANCE = 0.02                                     # relative, per channel (stated in docs)


def _photo(path, k, size, card_box, seed, quality=90):
    """A JPEG of a lit, textured floor holding a grey card (reflectance 0.3) at ``card_box``
    (x0, y0, x1, y1 of the photo): linear radiance × the camera gain ``k``, shot noise,
    sRGB-encoded, 8-bit. The light falls off smoothly across the card as across the floor
    (the same pattern in every photo, so the card's mean irradiance is the same)."""
    rng = np.random.default_rng(seed)
    w, h = size
    # the floor: a bright, saturated texture (parts of it clip at the object's exposure)
    floor = srgb_decode(rng.uniform(0.05, 0.95, (h // 8 + 1, w // 8 + 1, 3)))
    rad = np.kron(floor, np.ones((8, 8, 1)))[:h, :w] * 0.8
    x0, y0, x1, y1 = card_box
    u, v = np.meshgrid(np.linspace(0, 1, x1 - x0), np.linspace(0, 1, y1 - y0))
    light = (1.0 + 0.1 * (u - 0.5) - 0.08 * (v - 0.5))[..., None]        # mean 1
    rad[y0:y1, x0:x1] = 0.3 * light * np.array([1.0, 0.97, 0.9])   # a warm-ish light on it
    lin = rad * k
    lin = lin + rng.normal(0, 1, lin.shape) * 0.004 * np.sqrt(np.maximum(lin, 0))
    img = np.clip(srgb_encode(np.clip(lin, 0, None)), 0, 1)
    Image.fromarray((img * 255 + 0.5).astype(np.uint8)).save(path, quality=quality)
    return path


@pytest.fixture
def photos(tmp_path):
    obj = _photo(tmp_path / "object.jpg", K_OBJECT, (320, 240), (100, 80, 220, 170), 1)
    scene = _photo(tmp_path / "scene.jpg", K_SCENE, (400, 300), (40, 150, 200, 270), 2)
    # the boxes a user would draw: inside the card, off its edges
    return f"{obj}:104,84,216,166", f"{scene}:45,155,195,265"


def test_white_patch_gives_back_exposure_x2_and_warm_white_balance(photos):
    e = X.resolve_exposure(white_patch=photos)
    err = np.abs(np.asarray(e.gain) / TRUE_GAIN - 1)
    assert e.method == "reference" and err.max() < TOLERANCE, (e.gain, TRUE_GAIN, err)
    assert e.exposure_ev == pytest.approx(np.log2(LUMA @ TRUE_GAIN), abs=0.03)
    assert "same light" in e.assumed and "sRGB" in e.assumed
    j = e.to_json()
    assert j["detail"]["object_patch"]["clipped"] == 0 and j["gain"] == pytest.approx(e.gain)
    # without the sRGB decode the ratio of display values is far off: linearising matters
    naive = [np.asarray(Image.open(X.parse_patch(s)[0]).crop(X.parse_patch(s)[1]),
                        np.float64).reshape(-1, 3).mean(0) for s in photos]
    assert np.abs(naive[1] / naive[0] / TRUE_GAIN - 1).max() > 0.15


def test_default_is_gain_one_and_says_what_it_assumes():
    e = X.resolve_exposure()
    assert e.gain == (1.0, 1.0, 1.0) and e.is_identity and e.method == "assumed"
    assert "gain 1 assumed" in e.assumed and "--white-patch" in e.assumed
    assert e.to_json()["exposure_ev"] == 0.0
    g = X.resolve_exposure(gain=(0.5, 0.5, 0.25))
    assert g.method == "given" and g.white_balance[2] == pytest.approx(0.25 / 0.4819, rel=1e-3)


def test_grey_world_takes_out_a_colour_cast_and_keeps_the_luminance():
    rng = np.random.default_rng(0)
    grey = rng.uniform(0.2, 0.6, (500, 1)) * rng.uniform(0.9, 1.1, (500, 3))
    cast = np.array([1.3, 1.0, 0.7])
    e = X.gain_from_grey_world(grey * cast)
    wb = np.asarray(e.gain) * cast                      # grey again: equal channels
    assert np.abs(wb / wb.mean() - 1).max() < 0.03 and e.exposure_ev == pytest.approx(0, abs=0.03)
    assert "grey" in e.assumed and "coloured object" in e.assumed


@pytest.mark.parametrize("box, message", [
    ("0,0,999,10", "not inside"), ("10,10,5,20", "not inside")])
def test_bad_patches_name_the_photo(photos, box, message):
    path = X.parse_patch(photos[0])[0]
    with pytest.raises(ValueError, match=message):
        X.linear_patch(path, tuple(int(v) for v in box.split(",")))


def test_a_clipped_patch_is_refused(tmp_path):
    p = tmp_path / "white.png"
    Image.fromarray(np.full((20, 20, 3), 255, np.uint8)).save(p)
    with pytest.raises(ValueError, match="clipped"):
        X.linear_patch(p)
    with pytest.raises(ValueError, match="finite positive"):
        X.ExposureGain((1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="16 stops"):
        X.ExposureGain((1000.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="not both"):
        X.resolve_exposure(gain=(1, 1, 1), white_patch=(str(p), str(p)))


def test_compose_flags_exit_2_naming_the_photo(tmp_path, capsys):
    missing = tmp_path / "nope.jpg"
    rc = cli.main(["compose", str(tmp_path), "--object", "a=b", "--placement", "t.json",
                   "--out", str(tmp_path / "c"), "--white-patch", str(missing), str(missing)])
    assert rc == 2 and str(missing) in capsys.readouterr().err
    assert cli.main(["compose", str(tmp_path), "--object", "a=b", "--placement", "t.json",
                     "--out", str(tmp_path / "c"), "--exposure-gain", "1", "1"]) == 2
    assert cli.main(["compose", str(tmp_path), "--object", "a=b", "--placement", "t.json",
                     "--out", str(tmp_path / "c"), "--exposure-gain", "1", "1", "1",
                     "--grey-world"]) == 2                              # one or the other


def test_compose_multiplies_the_albedo_and_records_the_gain(tmp_path):
    """The default records gain 1 with its assumption and keeps the object's PLY; a gain
    writes objects/<name>.ply with albedo × gain, which the renderer then draws."""
    from test_composite import _nerf_folder, _probes_for, ball, plane, sun_map
    from comgs_dr.core.cameras import perspective
    from comgs_dr.core.similarity import Similarity, write_placements
    from comgs_dr.lighting import envmap as em
    from comgs_dr.sops import occlusion as occ
    from comgs_dr.stages.compose import ComposeConfig, compose
    from comgs_dr.stages.render_comp import load_comp_scene
    from comgs_dr.surfels.io import load_ply, save_ply
    from comgs_dr.train.run import write_run_info
    data = _nerf_folder(tmp_path / "data")
    run = tmp_path / "scene_run"
    write_run_info(run, data, "scene", 1, False)
    save_ply(plane(n=30), str(run / "point_cloud.ply"))
    d = tmp_path / "obj"
    d.mkdir()
    albedo = (0.6, 0.5, 0.4)
    p = ball((0, 0, 0), 0.3, albedo, n=600)
    save_ply(p, str(d / "point_cloud.ply"))
    _probes_for(p, count=60).save(d / "probes.npz")
    em.write_exr(tmp_path / "env.exr", sun_map(32), "octahedral")
    write_placements(tmp_path / "t.json", {"obj": Similarity(1.0, np.eye(3), np.array([0, 0, 0.3]))})
    cfg = ComposeConfig(shadow=occ.ShadowConfig(count=100, res=8, supersample=1),
                        scene_views=4, min_consistent=1)
    sensor = perspective([0.0, -3.0, 0.8], target=[0.0, 0.0, 0.3], res=16, fov=12)
    images = {}
    for key, exposure in (("none", None), ("gain", X.ExposureGain((0.5, 1.2, 3.0), "given")),
                          ("grey", "grey-world")):
        out = tmp_path / f"comp_{key}"
        s = compose(run, {"obj": d}, tmp_path / "t.json", out, env=tmp_path / "env.exr",
                    cfg=cfg, progress=False, exposure=exposure)
        m = json.loads((out / "composition.json").read_text())["objects"]["obj"]
        assert s["exposure"]["obj"] == m["exposure"]
        assert json.loads((out / "edit.json").read_text())["exposure"]["obj"] == m["exposure"]
        if key == "grey":                                   # albedo x gain is grey
            grey = np.multiply(albedo, m["exposure"]["gain"])
            assert m["exposure"]["method"] == "grey-world" and np.ptp(grey) < 1e-4
            assert LUMA @ m["exposure"]["gain"] == pytest.approx(1, abs=1e-5)
            continue
        images[key] = np.array(mi.render(load_comp_scene(out, "noshadow", sensors=[sensor],
                                                         rays=64)))
        if exposure is None:
            assert m["exposure"]["gain"] == [1.0, 1.0, 1.0]
            assert "gain 1 assumed" in m["exposure"]["assumed"]
            assert m["ply"] == str((d / "point_cloud.ply").resolve())
            assert not (out / "objects").exists()
        else:
            assert m["ply"] == str((out / "objects" / "obj.ply").resolve())
            a = load_ply(m["ply"]).to_numpy()["albedo"]
            assert np.allclose(a, np.minimum(np.multiply(albedo, (0.5, 1.2, 3.0)), 1), atol=1e-6)
            assert m["exposure"]["albedo_clipped"] == pytest.approx(1 / 3, abs=1e-6)  # blue
    centre = (slice(5, 11), slice(5, 11))                   # the ball fills these pixels
    ratio = images["gain"][centre][..., :3].sum((0, 1)) / images["none"][centre][..., :3].sum((0, 1))
    expect = np.minimum(np.multiply(albedo, (0.5, 1.2, 3.0)), 1) / albedo
    assert np.allclose(ratio, expect, rtol=0.1), (ratio, expect)
    from comgs_dr.eval.report import build_report
    page = build_report(tmp_path / "comp_none")
    assert "exposure gain (R, G, B)" in page and "gain 1 assumed" in page
    assert "0.500, 1.200, 3.000" in build_report(tmp_path / "comp_gain")
