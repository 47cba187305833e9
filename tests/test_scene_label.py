"""The indoor / outdoor classifier (``lighting.scene_label``) and its training stage."""
import json

import numpy as np
import pytest

from comgs_dr.core.equirect import equirect_directions
from comgs_dr.lighting import scene_label as S
from comgs_dr.lighting.hdr import expose


def _pano(h=32, sky=True, seed=0):
    """An [h, 2h, 3] HDR panorama: a blue sky over a darker textured ground (``sky``), or a
    dim grey ceiling with two bright warm lamps over a lit floor."""
    rng = np.random.default_rng(seed)
    d = equirect_directions(h, 2 * h)
    z = d[..., 2:3]
    noise = 1 + 0.3 * rng.random((h, 2 * h, 1))
    if sky:
        top = np.array([0.35, 0.55, 1.0]) * (0.6 + 0.4 * z)
        return np.where(z > 0, top, np.array([0.25, 0.2, 0.12]) * noise)
    room = np.where(z > 0.3, np.array([0.08, 0.08, 0.08]) * noise,
                    np.array([0.4, 0.3, 0.22]) * noise)
    lamp = (np.abs(d[..., 0:1] - 0.5) < 0.15) & (z > 0.5)
    return np.where(lamp, 30.0 * np.array([1.0, 0.85, 0.6]), room)


def _room(h=64, seed=0):
    """[h, 2h, 3]: a dark ceiling, lit walls, a warm floor and a bright window in one wall."""
    rng = np.random.default_rng(seed)
    d = equirect_directions(h, 2 * h)
    z = d[..., 2:3]
    noise = 1 + 0.3 * rng.random((h, 2 * h, 1))
    img = np.where(z > 0.5, np.array([0.05, 0.05, 0.05]) * noise,
                   np.array([0.3, 0.27, 0.22]) * noise)
    img = np.where(z < -0.1, np.array([0.35, 0.22, 0.12]) * noise, img)
    win = (np.abs(d[..., 0:1] - 0.7) < 0.2) & (z > 0.1) & (z < 0.45)
    return np.where(win, np.array([2.0, 2.0, 2.1]), img)


def _ldr(hdr, k=1.0):
    return np.clip(expose(hdr * k, 0.0), 0, 1)


def test_features_are_exposure_free_without_clipping():
    hdr = _pano(sky=True)
    mask = np.ones(hdr.shape[:2])
    a = S.label_features(_ldr(hdr, 0.5), mask)
    b = S.label_features(_ldr(hdr, 0.25), mask)
    assert a[S.FEATURES.index("clip_up")] == 0.0                # nothing clipped at 0.5
    rel = [S.FEATURES.index(f) for f in ("rel_top", "rel_up", "blue_up_minus_low", "sat_top")]
    np.testing.assert_allclose(a[rel], b[rel], atol=0.02)   # logs of +1e-3-shifted means
    assert a[S.FEATURES.index("rel_top")] > 0.3              # the sky is brighter than the mean
    assert a[S.FEATURES.index("blue_up_minus_low")] > 0.1
    assert a[S.FEATURES.index("seen_up")] == pytest.approx(1.0)


def test_unobserved_bands_and_bad_input():
    hdr = _pano(sky=True)
    mask = np.ones(hdr.shape[:2])
    mask[:10] = 0                                   # rows above 33.75° elevation unseen
    x = S.label_features(_ldr(hdr), mask)
    assert x[S.FEATURES.index("seen_top")] == pytest.approx(0.0, abs=1e-9)
    assert x[S.FEATURES.index("rel_top")] == 0.0 and np.isfinite(x).all()
    with pytest.raises(ValueError, match="nothing"):
        S.label_features(_ldr(hdr), np.zeros(hdr.shape[:2]))
    bad = _ldr(hdr)
    bad[3, 3, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        S.label_features(bad, np.ones(hdr.shape[:2]))
    with pytest.raises(ValueError, match="at least 2"):
        S.label_features(np.zeros((1, 8, 3)), np.ones((1, 8)))
    # any equirect size is read on the same 2:1 grid (a 3:1 trace, an odd height)
    wide = S.label_features(_ldr(_pano(32)[:, np.arange(96) * 64 // 96]), np.ones((32, 96)))
    np.testing.assert_allclose(wide, S.label_features(_ldr(_pano(32)), np.ones((32, 64))),
                               atol=0.05)
    assert np.isfinite(S.label_features(_ldr(_pano(32)[:31]), np.ones((31, 64)))).all()


def test_features_at_trace_size_match_small_size():
    """Read at 32 rows: a 256-row input gives nearly the features of its 32-row average."""
    from comgs_dr.lighting.hdr import area_resize_equirect
    hdr = _pano(256, sky=False)
    small = area_resize_equirect(hdr, 32, 64)
    a = S.label_features(_ldr(hdr), np.ones((256, 512)))
    b = S.label_features(_ldr(small), np.ones((32, 64)))
    i = [S.FEATURES.index(f) for f in ("rel_top", "rel_up", "rel_low", "blue_up_minus_low")]
    np.testing.assert_allclose(a[i], b[i], atol=0.15)        # sRGB averaging differs a little


def _logistic_data(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3)) * [1.0, 2.0, 0.5] + [0.0, 1.0, -1.0]
    beta = np.array([1.5, -0.8, 2.0])
    z = ((x - x.mean(0)) / x.std(0)) @ beta + 0.3
    y = (rng.random(n) < 1 / (1 + np.exp(-z))).astype(float)
    return x, y, beta


def test_fit_logistic_matches_a_generic_optimiser():
    """Newton's method against scipy's L-BFGS on the same penalised log loss."""
    from scipy.optimize import minimize
    x, y, beta = _logistic_data()
    m = S.fit_logistic(x, y, l2=5.0)
    zs = (x - x.mean(0)) / x.std(0)

    def loss(b):
        z = zs @ b[:-1] + b[-1]
        return np.mean(np.logaddexp(0, z) - y * z) + 5.0 / (2 * len(y)) * (b[:-1] ** 2).sum()
    ref = minimize(loss, np.zeros(4), method="L-BFGS-B", options={"gtol": 1e-10}).x
    np.testing.assert_allclose(m.coef, ref[:-1], atol=1e-4)
    assert m.bias == pytest.approx(ref[-1], abs=1e-4)
    np.testing.assert_allclose(m.coef, beta, atol=0.25)       # and near the generating truth
    with pytest.raises(ValueError, match="both classes"):
        S.fit_logistic(x, np.ones(len(x)))
    # integer weights are repeats: the same fit as the repeated rows
    rep = np.random.default_rng(1).integers(1, 4, len(y))
    mw = S.fit_logistic(x, y, l2=5.0, w=rep)
    mr = S.fit_logistic(np.repeat(x, rep, 0), np.repeat(y, rep), l2=5.0 * rep.sum() / len(y))
    np.testing.assert_allclose(mw.coef, mr.coef, atol=1e-6)
    assert mw.bias == pytest.approx(mr.bias, abs=1e-6)


def test_decide_margin_and_resolve_label():
    m = S.LabelModel(mean=[0.0] * len(S.FEATURES), std=[1.0] * len(S.FEATURES),
                     coef=[0.0] * len(S.FEATURES), bias=0.0, margin=0.2)
    assert m.decide(0.71) == "outdoor" and m.decide(0.69) == "unknown"
    assert m.decide(0.29) == "indoor" and m.decide(0.5) == "unknown"
    assert S.resolve_label("indoor", None, None) == ("indoor", None)
    with pytest.raises(ValueError, match="label must be"):
        S.resolve_label("space", None, None)
    hdr = _pano(sky=True)
    lab, p = S.resolve_label("auto", _ldr(hdr), np.ones(hdr.shape[:2]), m)
    assert lab == "unknown" and p == pytest.approx(0.5)        # a zero model is unsure


def test_shipped_model_reads_a_sky_and_a_room():
    """The shipped classifier on plain cases: a blue sky over ground is outdoor, a room with
    a dark ceiling and a window indoor; a dim ceiling with two very bright lamps is not
    read as outdoor (it is unsure: the lamps brighten the top band as a sky would)."""
    m = S.load_model()
    assert m.info and m.info["held_out"]                       # it records how it was made
    ones = np.ones((64, 128))
    for seed in range(3):
        lab_s, p_s = S.classify(_ldr(_pano(64, True, seed)), ones, m)
        lab_r, p_r = S.classify(_ldr(_room(64, seed)), ones, m)
        lab_l, p_l = S.classify(_ldr(_pano(64, False, seed)), ones, m)
        assert (lab_s, lab_r) == ("outdoor", "indoor"), (p_s, p_r)
        assert lab_l != "outdoor" and p_l < p_s, p_l


def test_model_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        S.load_model(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="readable"):
        S.load_model(tmp_path / "bad.json")
    x, y, _ = _logistic_data(200)
    xs = np.concatenate([x] * 4, 1)[:, :len(S.FEATURES)]
    m = S.fit_logistic(xs, y)
    p = S.save_model(m, tmp_path / "m.json")
    np.testing.assert_allclose(S.load_model(p).p_outdoor(xs[:20]), m.p_outdoor(xs[:20]))
    d = json.loads(p.read_text())
    d["features"] = ["other"]
    (tmp_path / "other.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match="other features"):
        S.load_model(tmp_path / "other.json")
    m.info = {"loss": float("nan")}                     # a record's NaN: null, strict JSON
    json.loads(S.save_model(m, tmp_path / "info.json").read_text(),
               parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    assert json.loads((tmp_path / "info.json").read_text())["info"]["loss"] is None
    m.coef[0] = float("nan")                           # the model itself: refused
    with pytest.raises(ValueError, match="non-finite"):
        S.save_model(m, tmp_path / "nan.json")
    assert not (tmp_path / "nan.json").exists()


def test_sample_weights_balance_groups_and_classes():
    from comgs_dr.stages.train_scene_label import sample_weights
    y = np.array([1, 1, 1, 1, 0, 0, 1, 1, 1, 1])
    g = np.array([0, 0, 0, 1, -2, -2, -1, -1, -1, -1])
    w = sample_weights(y, g)
    assert w.mean() == pytest.approx(1.0)
    assert w[y == 1].sum() == pytest.approx(w[y == 0].sum())
    # each outdoor group (maps 0, 1 and the skies) weighs the same
    np.testing.assert_allclose([w[g == k].sum() for k in (0, 1, -1)], w[g == 0].sum())


@pytest.mark.usefixtures("one_torch_thread")
def test_training_stage_tiny(tmp_path):
    """Two tiny maps (one named as a room), a few skies and rooms: the stage writes a model
    that loads, cross-validates each real map and scores the held-out one."""
    from comgs_dr.core.exr import write_image
    from comgs_dr.stages import train_scene_label as T
    maps = tmp_path / "maps"
    maps.mkdir()
    write_image(maps / "sky_a.exr", _pano(32, True, 1).astype(np.float32))
    write_image(maps / "sky_b.exr", _pano(32, True, 2).astype(np.float32))
    write_image(maps / "room_c.exr", _pano(32, False, 3).astype(np.float32))
    cfg = T.TrainSceneLabelConfig(out=tmp_path / "m.json", maps_dir=maps, held_out=("sky_b",),
                                  heights=(32,), draws_real=4, n_sky=3, n_rooms=3,
                                  draws_synth=1, n_masks=2, finished_rooms=1.0, room_spp=4)
    info = T.train(cfg, progress=False)
    m = S.load_model(cfg.out)
    assert [r["left_out"] for r in info["cross_validation"]] == ["room_c", "sky_a"]
    assert [r["map"] for r in info["held_out_scores"]] == ["sky_b"]
    # 4 draws of each training map, 3 skies, the rooms but a black one (eye inside a box)
    assert info["held_out_scores"][0]["draws"] == 4 and 4 * 2 + 3 + 1 <= info["draws"] <= 4 * 2 + 3 + 3
    for r in info["cross_validation"] + info["held_out_scores"]:
        assert r["correct"] + r["unknown"] + r["wrong"] == r["draws"]
    assert len(m.coef) == len(S.FEATURES) and np.isfinite(m.coef).all()


@pytest.mark.parametrize("flags", [["--finished-rooms", "1.5"], ["--finished-rooms", "-0.1"],
                                   ["--room-spp", "0"]])
def test_training_cli_refuses_bad_room_options(flags, tmp_path):
    import argparse
    from comgs_dr.stages import train_scene_label as T
    ap = argparse.ArgumentParser()
    T.add_arguments(ap)
    with pytest.raises(ValueError, match="finished-rooms"):
        T.run_from_args(ap.parse_args(["--out", str(tmp_path / "m.json"), *flags]))
