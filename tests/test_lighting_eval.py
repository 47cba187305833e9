"""Smoke test of benchmarks/lighting_eval.py on two tiny maps with simple masks."""
import importlib
import json
import re

import numpy as np
import pytest

from bench_module import load_benchmark

from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles

COVERAGES = (0.3, 0.5, 0.7, 0.9)       # one mask below 40 % (skipped), one per group


def _bench():
    return load_benchmark("lighting_eval")


def _report():
    return load_benchmark("lighting_eval_report")


def simple_mask_bank(n, h=64, w=128, seed=0, **_):
    """Masks observing everything below a latitude, chosen for the COVERAGES above."""
    d = equirect_directions(h, w)
    sa = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    out = []
    for i in range(n):
        c = COVERAGES[i % len(COVERAGES)]
        alpha = (d[..., 2] < 2 * c - 1).astype(np.float32)     # z < z0 covers c of the sphere
        normal = np.where(alpha[..., None] > 0, -d, 0).astype(np.float32)
        out.append({"alpha": alpha, "normal": normal,
                    "coverage": float((alpha * sa).sum() / sa.sum())})
    return out




@pytest.fixture
def pano_data(monkeypatch):
    """The real mask module with the simple mask provider."""
    mod = importlib.import_module("comgs_dr.data.pano_masks")
    monkeypatch.setattr(mod, "mask_bank", simple_mask_bank)
    return mod


def test_lighting_eval_smoke(tmp_path, pano_data, variant, capsys):
    import torch

    from comgs_dr.lighting.completion import (
        CompletionConfig,
        CompletionNet,
        save_weights,
    )
    from comgs_dr.lighting.envmap import write_exr
    maps = tmp_path / "maps"
    d = equirect_directions(16, 32)
    sky = 0.2 + 0.8 * np.clip(d[..., 2:], 0, 1) * np.array([0.6, 0.8, 1.0])
    write_exr(maps / "sky.exr", sky, "equirect")
    room = np.full((16, 32, 3), 0.3) + 0.1 * np.random.default_rng(0).random((16, 32, 3))
    room[3, 9] = 5e3                                          # a small, very bright lamp
    write_exr(maps / "room.exr", room, "equirect")
    (tmp_path / "labels.json").write_text(json.dumps({"room": "indoor", "sky": "outdoor"}))
    torch.manual_seed(0)
    net = CompletionNet(CompletionConfig(base_channels=8, levels=2, channel_mults=(1, 2, 2),
                                         embed_dim=16, groups=4))
    weights = save_weights(net, tmp_path / "net.pt")
    from comgs_dr.lighting.lights import LightHead, save_head
    head = save_head(LightHead(), tmp_path / "head.pt")       # untrained: gain softplus(~0)

    out = _bench().main(["--maps", str(maps), "--weights", str(weights), "--quick",
                         "--labels", str(tmp_path / "labels.json"), "--out",
                         str(tmp_path / "fig"), "--json", str(tmp_path / "r.json"),
                         "--examples", "1", "--light-head", str(head)])
    lines = capsys.readouterr().out.strip().splitlines()
    m = re.fullmatch(r"net_wins=(\d+)/(\d+) si_rmse_net=(\S+) si_rmse_best_baseline=(\S+)",
                     lines[-1])
    assert m, lines[-1]
    k, n = int(m.group(1)), int(m.group(2))
    assert n == 2 * 3 and 0 <= k <= n                 # 3 coverage groups x 2 metrics
    assert np.isfinite(float(m.group(3))) and np.isfinite(float(m.group(4)))
    assert out["skipped"] == 1                        # --quick: 2 masks per map, 30 % skipped
    methods = ["net", "net+lights", "net+sh", "net+sh+lights", "mean", "push_pull",
               "push_pull+lights", "sh"]
    assert [r["method"] for r in out["records"][:len(methods)]] == methods
    assert len(out["records"]) == 3 * len(methods)    # kept masks x methods
    assert out["ours"] == "net+sh+lights"
    assert re.fullmatch(r"light_angle_visible ours=\S+ best_baseline=\S+ \(\S+\)", lines[-2])
    assert re.fullmatch(r"light_angle_clear ours=\S+ best_baseline=\S+ \(\S+, n=\d+\)", lines[-3])
    for r in out["records"]:
        assert all(np.isfinite(r[key]) for key in ("si_rmse", "angular_deg", "nrmse",
                                                    "pano_si_rmse", "time_s",
                                                    "relight_psnr"))
        assert r["light_angle_deg"] is None or 0 <= r["light_angle_deg"] <= 180
        assert r["light_in_hole"] in (None, True, False)
        assert r["light_clear"] in (None, True, False)
    assert {r["label"] for r in out["records"]} == {"indoor", "outdoor"}
    for r in out["records"]:                     # the head's near-tie figure, +lights only
        d = r["light_dominance"]
        assert d is None or (r["method"].endswith("+lights") and d >= 1.0)
    assert (tmp_path / "fig" / "lighting_eval.png").stat().st_size > 0
    if out["best_baseline_light_angle"]:                     # per-map bars when comparable
        assert (tmp_path / "fig" / "lighting_eval_maps.png").stat().st_size > 0
    dump = json.loads((tmp_path / "r.json").read_text(),     # strict JSON: no NaN / Infinity
                      parse_constant=lambda c: pytest.fail(f"non-standard JSON {c}"))
    assert dump["summary"]["net_wins"] == k and len(dump["records"]) == 3 * len(methods)
    assert any(l.startswith("| coverage | light | method |") for l in lines)


def _two_suns(h, w, second, size=1):
    """[h, w, 3]: a dim sky, a size×size-pixel sun of power 1 at u = 0 and one of power
    ``second`` at u = ½ (the opposite azimuth), both just above the horizon."""
    img = np.full((h, w, 3), 1e-3)
    dw = pixel_solid_angles(h, w)[:, 0]
    rows = slice(h // 2 - size, h // 2)
    area = dw[rows].sum() * size
    img[rows, :size] = 1.0 / area
    img[rows, w // 2:w // 2 + size] = second / area
    return img


@pytest.mark.parametrize("second,size,clear", [(1.0, 1, False), (0.9, 1, False), (0.5, 1, True),
                                               (0.0, 1, True), (0.9, 3, False), (0.5, 3, True)])
def test_light_clear_needs_a_margin_over_the_second_light(second, size, clear):
    """Two suns of equal power are no clear dominant light; at half the power (or none) the
    first is. With 3×3-pixel suns the first fills the top 0.1 % of the sphere that seeds the
    dominant light, so the second is only found with the wider seeds (1 %) that "clear" uses.
    The angle and the visibility do not depend on the flag."""
    bench = _bench()
    h, w = 64, 128
    gt = _two_suns(h, w, second, size)
    objs = np.zeros((1, 4, 4, 3)), np.zeros((1, 4, 4, 3)), np.ones((4, 4), bool)
    out = bench.light_metrics(gt, gt, np.ones((h, w)), *objs)
    assert out["light_clear"] is clear
    assert out["light_in_hole"] is False and out["light_angle_deg"] == pytest.approx(0, abs=1e-3)
    recs = [{"light_in_hole": False, "light_clear": clear}, {"light_in_hole": True,
                                                            "light_clear": True}]
    assert _report()._split(recs, "clear") == ([recs[0]] if clear else [])


def test_held_out_selects_the_never_trained_maps(tmp_path, pano_data, variant, capsys):
    from comgs_dr.lighting.envmap import write_exr
    from comgs_dr.lighting.pano_data import HELD_OUT
    maps = tmp_path / "maps"
    d = equirect_directions(16, 32)
    sky = 0.2 + 0.8 * np.clip(d[..., 2:], 0, 1) * np.array([0.6, 0.8, 1.0])
    write_exr(maps / f"{HELD_OUT[0]}.exr", sky, "equirect")
    write_exr(maps / "trained_on.exr", sky, "equirect")
    out = _bench().main(["--maps", str(maps), "--held-out", "--quick", "--light-head", "none",
                         "--out", str(tmp_path / "fig"), "--examples", "0"])
    assert {r["map"] for r in out["records"]} == {HELD_OUT[0]}
    assert {r["label"] for r in out["records"]} == {"outdoor"}
    # an unlabelled map takes --default-label; "auto" records the classifier's answer
    from comgs_dr.lighting import scene_label
    out = _bench().main(["--maps", str(maps), "--quick", "--light-head", "none",
                         "--default-label", "auto", "--out", str(tmp_path / "fig"),
                         "--examples", "0"])
    for r in out["records"]:
        assert r["label_requested"] == "auto" and 0.0 <= r["p_outdoor"] <= 1.0
        assert r["label"] == scene_label.load_model().decide(r["p_outdoor"])
    counts = _report().label_counts(out["records"])        # one count per sample, per map
    n = len({(r["map"], r["mask"], r["draw"]) for r in out["records"]})
    assert sum(sum(c.values()) for c in counts.values()) == n
    assert "### Labels given by the classifier" in capsys.readouterr().out
    # --scene-label: another classifier decides "auto" (here one that answers indoor always)
    m = scene_label.load_model()
    always_indoor = scene_label.LabelModel(m.mean, m.std, [0.0] * len(m.coef), -20.0, m.margin)
    path = scene_label.save_model(always_indoor, tmp_path / "indoor.json")
    out = _bench().main(["--maps", str(maps), "--quick", "--light-head", "none",
                         "--default-label", "auto", "--scene-label", str(path),
                         "--out", str(tmp_path / "fig"), "--examples", "0"])
    assert out["records"] and {r["label"] for r in out["records"]} == {"indoor"}
    assert all(r["p_outdoor"] < 1e-6 for r in out["records"])
    with pytest.raises(FileNotFoundError, match="--scene-label: no such file"):
        _bench().main(["--maps", str(maps), "--quick", "--scene-label", str(tmp_path / "x.json")])
    with pytest.raises(ValueError, match="none is"):         # no map is labelled auto
        _bench().main(["--maps", str(maps), "--quick", "--default-label", "indoor",
                       "--scene-label", str(path)])
    write_exr(maps / "trained_on.hdr", sky, "equirect")       # "trained_on" twice
    with pytest.raises(ValueError, match="trained_on.exr, trained_on.hdr"):
        _bench().main(["--maps", str(maps), "--quick"])
    (maps / "trained_on.hdr").unlink()
    (maps / f"{HELD_OUT[0]}.exr").unlink()
    with pytest.raises(FileNotFoundError, match="--held-out"):
        _bench().main(["--maps", str(maps), "--held-out", "--quick"])


def test_draws_pool_independent_rotations_and_report_each(tmp_path, pano_data, variant, capsys):
    from comgs_dr.lighting.envmap import write_exr
    maps = tmp_path / "maps"
    d = equirect_directions(16, 32)
    sky = 0.2 + 0.8 * np.clip(d[..., 2:], 0, 1) * np.array([0.6, 0.8, 1.0])
    sky[4, 3] = 2e3                                                      # a sun to rotate
    write_exr(maps / "sky.exr", sky, "equirect")
    common = ["--maps", str(maps), "--quick", "--light-head", "none", "--out",
              str(tmp_path / "fig"), "--examples", "0", "--seed", "3"]
    one = _bench().main(common)
    capsys.readouterr()
    two = _bench().main(common + ["--draws", "2"])
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(two["records"]) == 2 * len(one["records"])
    assert {r["draw"] for r in two["records"]} == {3, 4}
    first = [r for r in two["records"] if r["draw"] == 3]
    assert [(r["method"], r["shift"]) for r in first] == \
        [(r["method"], r["shift"]) for r in one["records"]]            # draw 0 = the single run
    second = [r for r in two["records"] if r["draw"] == 4]
    assert [r["shift"] for r in second] != [r["shift"] for r in first]   # another rotation
    n = len({(r["map"], r["mask"]) for r in one["records"]})
    assert [l.split()[1:3] for l in lines if l.startswith("draw seed=")] == \
        [["seed=3", f"samples={n}"], ["seed=4", f"samples={n}"]]
    assert lines[-1].startswith("net_wins=") and lines[-2].startswith("light_angle_visible")
    with pytest.raises(SystemExit):
        _bench().main(common + ["--draws", "0"])


def test_bad_maps_are_all_named_before_any_work(tmp_path, monkeypatch, variant):
    """A folder with a good map, a black one, one with a NaN and an unreadable file: one
    ValueError names the three bad ones, raised before the mask bank (no minutes lost)."""
    from comgs_dr.lighting.envmap import write_exr
    maps = tmp_path / "maps"
    d = equirect_directions(16, 32)
    sky = 0.2 + 0.8 * np.clip(d[..., 2:], 0, 1) * np.array([0.6, 0.8, 1.0])
    write_exr(maps / "good.exr", sky, "equirect")
    write_exr(maps / "black.exr", np.zeros((16, 32, 3)), "equirect")
    bad = sky.copy()
    bad[4, 4] = np.nan
    write_exr(maps / "nan.exr", bad, "equirect")
    (maps / "broken.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 10 +X 20\n")
    mod = importlib.import_module("comgs_dr.data.pano_masks")
    monkeypatch.setattr(mod, "mask_bank", lambda *a, **k: pytest.fail("work before the check"))
    with pytest.raises(ValueError, match=r"3 of 4 maps") as e:
        _bench().main(["--maps", str(maps), "--quick", "--light-head", "none"])
    msg = str(e.value)
    assert all(n in msg for n in ("black.exr", "nan.exr", "broken.hdr"))
    assert "good.exr" not in msg


def test_dominance_table_splits_by_the_warning():
    from comgs_dr.lighting.lights import DOMINANCE_MARGIN
    rec = lambda d, ang, hole=False, m="ours": {"method": m, "light_in_hole": hole,  # noqa: E731
                                                  "light_angle_deg": ang, "light_dominance": d}
    rows = _report().dominance_table(
        [rec(None, 10.0), rec(1.1, 80.0), rec(1.2, 20.0), rec(DOMINANCE_MARGIN, 5.0),
         rec(3.0, 45.0), rec(1.1, 90.0, hole=True), rec(1.1, 90.0, m="mean"),
         rec(1.1, None)], "ours")
    assert [r["n"] for r in rows] == [1, 2, 2]
    assert [r["light_angle"] for r in rows] == [10.0, 50.0, 25.0]
    assert [r["over_30"] for r in rows] == [0.0, 0.5, 0.5]


def test_maps_the_models_were_trained_on_are_named(tmp_path, capsys):
    """A map a model was fitted on (its model card's list, matched by file stem) is named
    before the run and in the result; a model without a card is said to be unknown."""
    from comgs_dr.lighting import pano_data
    from comgs_dr.lighting.envmap import write_exr
    from comgs_dr.lighting.lights import DEFAULT_HEAD, LightHead, save_head
    CV_HEADS = load_benchmark("cv_heads").CV_HEADS
    card = pano_data.trained_maps(DEFAULT_HEAD)
    # the shipped head saw every shared map; each held-out map has a kept fold without it
    assert card and set(pano_data.HELD_OUT) <= card
    for stem in pano_data.HELD_OUT:
        fold = pano_data.trained_maps(CV_HEADS / f"{stem}.pt")
        assert fold and stem not in fold and fold < card
    trained = sorted(card - set(pano_data.HELD_OUT))[0]
    maps = tmp_path / "maps"
    sky = np.full((8, 16, 3), 0.5)
    for stem in (trained, "fresh", pano_data.HELD_OUT[0]):
        write_exr(maps / f"{stem}.exr", sky, "equirect")
    bench = _bench()
    ov = bench.training_overlap(bench.parse_args(["--maps", str(maps)]))
    assert ov == {"trained_on": {trained: ["completion net", "light head", "scene label"]},
                  "no_card": []}
    # labels given, no head: only the net; a head saved by hand has no card
    head = save_head(LightHead(), tmp_path / "head.pt")
    ov = bench.training_overlap(bench.parse_args(["--maps", str(maps), "--default-label",
                                                  "outdoor", "--light-head", str(head)]))
    assert ov == {"trained_on": {trained: ["completion net"]}, "no_card": ["light head"]}
    ov = bench.training_overlap(bench.parse_args(["--maps", str(maps), "--held-out"]))
    assert ov == {"trained_on": {}, "no_card": []}                # scored with its fold
    ov = bench.training_overlap(bench.parse_args(["--maps", str(maps), "--held-out",
                                                  "--light-head", str(DEFAULT_HEAD)]))
    assert ov == {"trained_on": {pano_data.HELD_OUT[0]: ["light head"]}, "no_card": []}
    bench.print_overlap({"trained_on": {trained: ["light head"]}, "no_card": ["scene label"]})
    out = capsys.readouterr().out
    assert f"WARNING: {trained} was in the training data of the light head" in out
    assert "the scene label has no model card" in out


def test_cv_heads_are_checked_per_map(tmp_path, capsys):
    """--cv-heads scores each map with its own fold head: a map without one is named before
    any work, and a fold head whose card lists its own map is a training overlap."""
    import pytest as _pytest

    from comgs_dr.lighting import pano_data
    from comgs_dr.lighting.envmap import write_exr
    from comgs_dr.lighting.lights import LightHead, save_head
    maps, cv = tmp_path / "maps", tmp_path / "cv"
    for stem in ("a", "b"):
        write_exr(maps / f"{stem}.exr", np.full((8, 16, 3), 0.5), "equirect")
    bench = _bench()
    args = bench.parse_args(["--maps", str(maps), "--cv-heads", str(cv), "--default-label",
                             "outdoor"])
    with _pytest.raises(FileNotFoundError, match="no such folder"):
        bench.cv_head_paths(args, bench.list_maps(maps))
    for stem, others in (("a", ["b"]), ("b", ["a", "b"])):
        save_head(LightHead(), cv / f"{stem}.pt")
        (cv / f"{stem}.json").write_text(json.dumps({"maps": others}))
    (cv / "b.pt").unlink()
    with _pytest.raises(FileNotFoundError, match="no head for b"):
        bench.cv_head_paths(args, bench.list_maps(maps))
    save_head(LightHead(), cv / "b.pt")
    ov = bench.training_overlap(args)
    assert ov == {"trained_on": {"b": ["cv light head"]}, "no_card": []}
    with _pytest.raises(SystemExit):
        bench.parse_args(["--maps", str(maps), "--cv-heads", str(cv), "--light-head", "x.pt"])
    assert pano_data.trained_maps(cv / "a.pt") == frozenset({"b"})


def _angle_records(per_map: dict) -> list:
    """Records of two methods: {map: [(ours, base) angle per sample]}, all light-visible."""
    out = []
    for m, pairs in per_map.items():
        for k, (o, b) in enumerate(pairs):
            for me, ang in (("ours", o), ("base", b)):
                out.append({"map": m, "mask": k, "method": me, "light_angle_deg": ang,
                            "light_in_hole": False, "light_clear": True})
    return out


def test_angle_ratio_ci_resamples_maps():
    le = _report()
    same = _angle_records({"a": [(5.0, 10.0), (15.0, 30.0)], "b": [(2.0, 4.0)]})
    ci = le.angle_ratio_ci(same, "ours", "base")
    assert ci["ratio"] == pytest.approx(0.5) and ci["maps"] == 2
    assert ci["lo"] == pytest.approx(0.5) and ci["hi"] == pytest.approx(0.5)   # every map ½
    mixed = _angle_records({"a": [(5.0, 10.0)] * 3, "b": [(40.0, 20.0)] * 3,
                            "c": [(1.0, 10.0)] * 3})
    ci = le.angle_ratio_ci(mixed, "ours", "base", n_boot=4000)
    assert ci["ratio"] == pytest.approx(46.0 / 40.0)                    # pooled means
    assert ci["lo"] < ci["ratio"] < ci["hi"]
    assert ci["lo"] <= 0.55 and ci["hi"] >= 1.5                          # one map flips it
    hole = [dict(r, light_in_hole=True) for r in same]
    assert np.isnan(le.angle_ratio_ci(hole, "ours", "base")["ratio"])     # nothing visible
