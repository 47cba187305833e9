"""Completion training data: energy-preserving resizes and splats, auto exposure, procedural
skies/rooms, traced masks, training batches, loss, and a tiny end-to-end training run."""
import json

import numpy as np
import pytest
import torch

from comgs_dr.core import colorspace, equirect
from comgs_dr.data import pano_masks
from comgs_dr.lighting import completion as C
from comgs_dr.lighting import pano_data as P
from comgs_dr.lighting.envmap import write_exr
from comgs_dr.lighting.hdr import area_resize_equirect


def _power(img):
    return (img * equirect.solid_angle_image(*img.shape[:2])[..., None]).sum((0, 1))


def test_solid_angles_sum_to_4pi():
    assert equirect.solid_angle_image(16, 32).shape == (16, 32)
    assert abs(equirect.solid_angle_image(16, 32).sum() - 4 * np.pi) < 1e-9


def test_area_resize_preserves_power_of_a_tiny_sun():
    img = np.full((64, 128, 3), 0.5, np.float32)
    img[20, 37] = 1e6
    for h, w in ((16, 32), (15, 37), (100, 200)):
        small = area_resize_equirect(img, h, w)
        np.testing.assert_allclose(_power(small), _power(img), rtol=1e-5)
    np.testing.assert_allclose(area_resize_equirect(np.full((30, 50, 3), 2.0), 7, 9), 2.0, rtol=1e-6)
    with pytest.raises(ValueError, match="h, w >= 1"):
        area_resize_equirect(img, 0, 32)


def test_splat_direction_deposits_exact_power():
    img = np.zeros((32, 64, 3))
    d = np.array([0.3, -0.5, 0.6])
    P._splat_direction(img, d / np.linalg.norm(d), np.array([2.0, 1.0, 0.5]))
    np.testing.assert_allclose(_power(img), [2.0, 1.0, 0.5], rtol=1e-9)


def test_auto_exposure_scale_and_errors():
    rng = np.random.default_rng(0)
    img = rng.uniform(0.01, 2.0, (16, 32, 3))
    k = P.auto_exposure(img)
    assert k > 0 and abs(P.auto_exposure(img * 8.0) * 8.0 / k - 1) < 1e-6
    with pytest.raises(ValueError, match="black"):
        P.auto_exposure(np.zeros((8, 16, 3)))
    bad = img.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        P.auto_exposure(bad)
    with pytest.raises(ValueError, match="equirect"):
        P.auto_exposure(np.ones((8, 16)))


def test_load_map_resizes_files_and_rejects_nan(tmp_path):
    img = np.full((40, 80, 3), 0.25, np.float32)
    img[10, 10] = 1e6
    write_exr(tmp_path / "a.exr", img, "equirect")
    out = P.load_map(tmp_path / "a.exr", 16, 32)
    assert out.shape == (16, 32, 3) and np.isfinite(out).all()
    np.testing.assert_allclose(_power(out), _power(img), rtol=1e-4)
    img[3, 3] = np.nan
    write_exr(tmp_path / "b.exr", img, "equirect")
    with pytest.raises(ValueError, match="NaN"):
        P.load_map(tmp_path / "b.exr", 16, 32)


def test_map_files_names_every_unusable_map(tmp_path):
    img = np.full((16, 32, 3), 0.25, np.float32)
    write_exr(tmp_path / "good.exr", img, "equirect")
    write_exr(tmp_path / "held.exr", img, "equirect")
    (tmp_path / "notes.txt").write_text("not a map")
    assert [p.name for p in P.map_files(tmp_path, exclude=("held",))] == ["good.exr"]
    write_exr(tmp_path / "black.exr", np.zeros_like(img), "equirect")
    write_exr(tmp_path / "oct.exr", np.ones((8, 8, 3)), "octahedral")
    (tmp_path / "cut.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 8\n")
    with pytest.raises(ValueError, match="3 of 4 maps") as e:
        P.map_files(tmp_path, exclude=("held",))
    assert all(n in str(e.value) for n in ("black.exr", "oct.exr", "cut.hdr"))


@pytest.mark.parametrize("name,card,expect", [
    ("net.pt", {"data": {"poly_haven": ["a", "b"]}}, {"a", "b"}),          # train-completion
    ("net.pt", {"data": {"poly_haven": ["a"], "init_maps": ["b", "z"]}}, {"a", "b", "z"}),
    ("net.pt", {"data": {"poly_haven": ["a"], "init_maps": None}}, {"a"}),  # --init: no card
    ("head.pt", {"maps": ["c"], "held_out": ["d"]}, {"c"}),                 # train-light-head
    ("label.json", {"format": "x", "info": {"maps": ["e"]}}, {"e"}),        # train-scene-label
    ("head.pt", {"maps": "c"}, None),                                       # not a list
    ("head.pt", ["c"], None),
    ("head.pt", None, None),                                                # no card
])
def test_trained_maps_reads_each_model_card(tmp_path, name, card, expect):
    card_path = tmp_path / (name if name.endswith(".json") else name.replace(".pt", ".json"))
    if card is not None:
        card_path.write_text(json.dumps(card))
    got = P.trained_maps(tmp_path / name)
    assert got == (None if expect is None else frozenset(expect))
    card_path.write_text("{not json")
    assert P.trained_maps(tmp_path / name) is None


def test_rotate_u_round_trip():
    x = np.random.default_rng(1).random((4, 8, 3))
    np.testing.assert_array_equal(P.rotate_u(P.rotate_u(x, 3), -3), x)


def test_sunsky_panorama_has_sky_sun_and_ground():
    rng = np.random.default_rng(3)
    found_sun = 0
    for _ in range(4):
        img = P.sunsky_panorama(rng, 32, 64)
        assert img.shape == (32, 64, 3) and np.isfinite(img).all() and img.min() >= 0
        lum = img @ colorspace.LUMA
        assert lum[:16].mean() > 0 and lum[16:].mean() > 0          # sky and lit ground
        found_sun += lum.max() > 100 * np.median(lum)
    assert found_sun >= 2                                             # 85 % of skies have a sun


def test_room_panorama_is_lit_by_emitters():
    img = P.room_panorama(np.random.default_rng(5), 16, 32, spp=4)
    assert img.shape == (16, 32, 3) and np.isfinite(img).all() and img.min() >= 0
    lum = img @ colorspace.LUMA
    assert lum.max() > 5 * np.median(lum) > 0


def test_room_bulbs_are_small_bright_and_inside_the_room():
    from comgs_dr.lighting.pano_data import _room_dict
    n_bulbs = 0
    for seed in range(12):
        assert not any(k.startswith("bulb") for k in _room_dict(np.random.default_rng(seed))[0])
        d, _, _ = _room_dict(np.random.default_rng(seed), bulbs=True)
        half = np.array([d["floor"]["to_world"].matrix[0, 0], d["floor"]["to_world"].matrix[1, 1]])
        top = d["ceiling"]["to_world"].matrix[2, 3]
        for k, b in d.items():
            if not k.startswith("bulb"):
                continue
            n_bulbs += 1
            c = np.array(b["center"])
            assert 0.02 <= b["radius"] <= 0.08
            assert (np.abs(c[:2]) + b["radius"] < half).all() and b["radius"] < c[2] < top
            rad = np.array(b["emitter"]["radiance"]["value"])
            assert rad.max() == pytest.approx(rad[0]) and 10 ** 2.5 <= rad[0] <= 10 ** 4.5
    assert 3 <= n_bulbs <= 40                       # about half the rooms, 1-4 bulbs each


def test_mask_bank_masks_and_normals():
    masks = pano_masks.mask_bank(4, 16, 32, seed=2, n_surfels=4000, points_per_scene=2)
    assert len(masks) == 4
    for m in masks:
        a, n = m["alpha"], m["normal"]
        assert a.shape == (16, 32) and n.shape == (16, 32, 3)
        assert a.min() >= 0 and a.max() <= 1 + 1e-6
        sa = equirect.solid_angle_image(16, 32)
        assert abs((a * sa).sum() / sa.sum() - m["coverage"]) < 1e-3
        cov = a > 0.5
        np.testing.assert_allclose(np.linalg.norm(n[cov], axis=-1), 1.0, atol=1e-3)
        assert 0.05 < m["coverage"] < 1.0


def test_completion_loss_zero_at_target_and_normalised():
    t = torch.rand(2, 3, 16, 32)
    assert P is not None
    from comgs_dr.stages.train_completion import completion_loss
    assert completion_loss(t, t, 16, 32).item() == 0.0
    # the same relative error weighs the same on a dark (EV -5) and a bright target
    dark, bright = t * 0.01, t
    l_dark = completion_loss(dark * 1.1, dark, 16, 32).item()
    l_bright = completion_loss(bright * 1.1, bright, 16, 32).item()
    assert l_dark > 0.1 * l_bright


def test_completion_loss_lowfreq_terms_see_colour_casts_not_zero_mean_noise():
    from comgs_dr.stages.train_completion import completion_loss
    t = torch.rand(2, 3, 16, 32) + 0.5
    checker = ((torch.arange(16)[:, None] + torch.arange(32)[None]) % 2 * 2 - 1).float()  # ±1
    noise, cast = t + 0.1 * checker, t + 0.1
    base_noise, base_cast = completion_loss(noise, t, 16, 32), completion_loss(cast, t, 16, 32)
    # the per-pixel L1 cannot tell a ±0.1 checker from a +0.1 cast ...
    assert abs(base_noise.item() - base_cast.item()) < 0.05 * base_cast.item()
    # ... the block averages can: the cast costs (1 + 2·lowfreq)×, the checker barely more
    lf_noise = completion_loss(noise, t, 16, 32, lowfreq=0.5, pools=(4, 8)).item()
    lf_cast = completion_loss(cast, t, 16, 32, lowfreq=0.5, pools=(4, 8)).item()
    assert lf_cast == pytest.approx(2.0 * base_cast.item(), rel=1e-4)
    assert lf_noise < 1.05 * base_noise.item()
    with pytest.raises(ValueError, match="does not divide"):
        completion_loss(t, t, 16, 32, lowfreq=0.5, pools=(5,))


def test_lr_schedule_follows_the_time_fraction():
    from comgs_dr.stages.train_completion import TrainCompletionConfig, _lr
    cfg = TrainCompletionConfig(lr=1e-3, warmup=10)
    assert _lr(0, 0.0, cfg) == pytest.approx(1e-4)
    lrs = [_lr(100, f, cfg) for f in np.linspace(0, 1, 11)]
    assert lrs[0] == pytest.approx(1e-3) and lrs[-1] == pytest.approx(5e-5)
    assert lrs[5] == pytest.approx(0.525e-3)
    assert all(a > b for a, b in zip(lrs, lrs[1:]))


def test_interior_colours_are_valid_and_not_all_grey():
    rng = np.random.default_rng(0)
    c = np.array([P.interior_colour(rng, 0.3, 0.85) for _ in range(400)])
    assert c.min() >= 0.02 and c.max() <= 0.95
    sat = (c.max(1) - c.min(1)) / c.max(1)
    assert np.mean(sat > 0.2) > 0.25 and np.mean(sat < 0.1) > 0.2   # both tinted and near-grey
    warm = (c[:, 0] > c[:, 2]).mean()
    assert warm > 0.6                                               # interiors lean warm


@pytest.fixture(scope="module")
def tiny_training(tmp_path_factory):
    from comgs_dr.stages.train_completion import (
        TrainCompletionConfig,
        build_data,
        train,
    )
    d = tmp_path_factory.mktemp("tc")
    maps = d / "maps"
    maps.mkdir()
    rng = np.random.default_rng(0)
    write_exr(maps / "yard.exr", rng.uniform(0.1, 2, (32, 64, 3)).astype(np.float32), "equirect")
    write_exr(maps / "held.exr", rng.uniform(0.1, 2, (32, 64, 3)).astype(np.float32), "equirect")
    cfg = TrainCompletionConfig(out=d / "w.pt", data_dir=d / "data", maps_dir=maps,
                                held_out=("held",), n_sky=3, n_rooms=2, n_masks=4, room_spp=1,
                                height=16, width=32, base_channels=8, minutes=0.05,
                                max_steps=12, batch=2, net={"levels": 2,
                                                           "channel_mults": (1, 2, 2)})
    info = train(cfg, progress=False, command="test")
    return cfg, info, build_data(cfg, progress=False)


def test_training_data_excludes_held_out_maps(tiny_training):
    cfg, info, data = tiny_training
    assert info["data"]["poly_haven"] == ["yard"]
    assert data["maps"].shape == (1 + 3 + 2, 16, 32, 3) and np.isfinite(data["maps"]).all()
    assert sorted(set(data["source"].tolist())) == [0, 1, 2]


def test_sampler_batches(tiny_training):
    from comgs_dr.stages.train_completion import Sampler
    cfg, _, data = tiny_training
    s = Sampler(data, cfg, 0)
    rgb, nor, msk, tgt, evs, lab = s.batch(6, "ev")
    assert rgb.shape == tgt.shape == nor.shape == (6, 3, 16, 32) and msk.shape == (6, 1, 16, 32)
    assert ((evs >= C.EV_MIN) & (evs <= 0)).all() and lab.max() <= 2
    assert float(rgb[(msk == 0).expand_as(rgb)].abs().max()) == 0.0   # nothing in the holes
    assert float(rgb[(msk > 0).expand_as(rgb)].mean()) > 0.0          # un-premultiplied colour
    rgb0, *_, tgt0, evs0, _ = s.batch(4, "zero")
    assert (evs0 == 0).all()


def test_tiny_training_writes_loadable_weights(tiny_training):
    cfg, info, _ = tiny_training
    assert info["steps"] >= 1 and np.isfinite(info["history"][-1]["loss"])
    model = C.load_weights(cfg.out)
    assert model.config.train_resolution == (16, 32)
    log = json.loads(cfg.out.with_suffix(".json").read_text())
    assert log["command"] == "test" and log["data"]["held_out"] == ["held"]
    out = C.NetworkBackend(model).complete(np.zeros((16, 32, 3), np.float32),
                                           np.zeros((16, 32, 3), np.float32),
                                           np.zeros((16, 32), np.float32))
    assert all(np.isfinite(v).all() for v in out.values())


def test_train_completion_cli(tmp_path, capsys):
    from comgs_dr import cli
    maps = tmp_path / "maps"
    maps.mkdir()
    write_exr(maps / "a.exr", np.full((16, 32, 3), 0.5, np.float32), "equirect")
    out = tmp_path / "w.pt"
    argv = ["train-completion", "--out", str(out), "--data-dir", str(tmp_path / "d"), "--maps",
            str(maps), "--minutes", "0.02", "--max-steps", "2", "--skies", "1", "--rooms", "1",
            "--masks", "2", "--room-spp", "1", "--res", "16", "--channels", "8", "--batch", "2",
            "--quiet"]
    assert cli.main(argv) == 0
    assert C.load_weights(out).config.train_resolution == (16, 32)
    assert cli.main(argv + ["--res", "24"]) == 2                      # not a multiple of 16
    assert "multiple of 16" in capsys.readouterr().err


def test_augmented_view_keeps_power_and_masks_the_ldr():
    """Rotation and mirroring keep each row's power; with no exposure or white-balance jitter
    the draw is k × the map; the LDR is 0 outside the (repeated) mask."""
    from comgs_dr.core.colorspace import LUMA
    from comgs_dr.lighting.hdr import expose
    from comgs_dr.lighting.pano_data import augmented_view
    rng = np.random.default_rng(0)
    hdr = rng.random((16, 32, 3)) * np.linspace(0.1, 3.0, 16)[:, None, None]
    masks = (rng.random((3, 8, 16)) > 0.4).astype(np.float32)
    for seed in range(6):
        m, a, ldr = augmented_view(np.random.default_rng(seed), hdr, 2.0, masks, 0.0, 0.0, 0.5)
        np.testing.assert_allclose((m @ LUMA).sum(1), 2.0 * (hdr @ LUMA).sum(1), rtol=1e-12)
        assert a.shape == (16, 32) and set(np.unique(a)) <= {0.0, 1.0}
        assert np.all(ldr[a <= 0.5] == 0)
        np.testing.assert_allclose(ldr[a > 0.5], expose(m, 0.0)[a > 0.5])


def test_finished_room_is_repainted_and_lit_by_strips():
    """_finish_room: pale ceiling (saturation ≤ 0.06), strip lights facing down at the
    ceiling, uplights facing up below it; the plain room (same seed) has none of them and
    its random stream is unchanged by the option's existence."""
    from comgs_dr.lighting.pano_data import _room_dict
    n_up = 0
    for seed in range(8):
        plain, _, _ = _room_dict(np.random.default_rng(seed))
        d, _, _ = _room_dict(np.random.default_rng(seed), finished=True)
        assert not any(k.startswith(("strip", "uplight")) for k in plain)
        assert plain.keys() <= d.keys()
        for k in plain:                 # same random stream: geometry and lights unchanged
            if k.startswith(("obj", "lamp", "window")):
                a, b = plain[k], d[k]
                assert a.get("center") == b.get("center") and a.get("radius") == b.get("radius")
                if "to_world" in a:
                    np.testing.assert_array_equal(np.array(a["to_world"].matrix),
                                                  np.array(b["to_world"].matrix))
        top = d["ceiling"]["to_world"].matrix[2, 3]
        ceil = np.array(d["ceiling"]["bsdf"]["bsdf"]["reflectance"]["value"])
        assert ceil.min() >= 0.7 * 0.94 - 1e-9 and ceil.max() - ceil.min() <= 0.06 * ceil.max() + 1e-9
        strips = [v for k, v in d.items() if k.startswith("strip")]
        assert 2 <= len(strips) <= 8
        for s in strips:
            m = np.array(s["to_world"].matrix)
            assert m[2, 3] == pytest.approx(top - 0.01)
            assert (m[:3, :3] @ np.array([0.0, 0.0, 1.0]))[2] < 0          # facing down
        for k, v in d.items():
            if k.startswith("uplight"):
                n_up += 1
                m = np.array(v["to_world"].matrix)
                assert (m[:3, :3] @ np.array([0.0, 0.0, 1.0]))[2] > 0 and m[2, 3] < top
    assert n_up > 0
    img = P.room_panorama(np.random.default_rng(1), 16, 32, spp=4, finished=True)
    assert np.isfinite(img).all() and img.min() >= 0 and img.max() > 0


def test_fine_tuned_card_names_the_init_weights_maps(tmp_path):
    """train-completion --init W records W's maps (``data.init_maps``), so trained_maps of
    the fine-tuned weights names every map they saw."""
    from comgs_dr.stages.train_completion import _init_maps
    (tmp_path / "w.json").write_text(json.dumps({"data": {"poly_haven": ["b", "a"]}}))
    assert _init_maps(tmp_path / "w.pt") == ["a", "b"]
    assert _init_maps(None) is None and _init_maps(tmp_path / "none.pt") is None
    card = {"data": {"poly_haven": ["c"], "init_maps": _init_maps(tmp_path / "w.pt")}}
    (tmp_path / "ft.json").write_text(json.dumps(card))
    assert P.trained_maps(tmp_path / "ft.pt") == frozenset({"a", "b", "c"})
