"""benchmarks/light_ranking.py: the top-1 and log-error scores, and a smoke run."""
from pathlib import Path

import numpy as np
import pytest

from bench_module import BENCHMARKS, load_benchmark

from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles


def _bench():
    return load_benchmark("light_ranking")


def _row(name, true, pred):
    return {"map": name, "regions": [{"true": t, "seen": p, "head": p, "net": p}
                                     for t, p in zip(true, pred)]}


def test_top1_counts_hits_and_skips_near_ties():
    b = _bench()
    rows = [_row("a", [3.0, 1.0], [2.0, 1.0]),         # right
            _row("a", [3.0, 1.0], [1.0, 2.0]),         # wrong
            _row("b", [1.1, 1.0, 0.1], [0.0, 5.0, 1.0])]  # wrong, but a near tie (1.1×)
    f = b.predictors()["seen"]
    assert b.score(rows, f, 1.0) == (pytest.approx(1 / 3), 3, {"a": [1, 2], "b": [0, 1]})
    assert b.score(rows, f, 1.5) == (pytest.approx(1 / 2), 2, {"a": [1, 2]})
    # |log(2/3)|, |log 1|, |log(1/3)|, |log 2|, |log 0 → 1e-12 / 1.1|, |log 5|, |log 10|
    want = np.mean(np.abs(np.log([2 / 3, 1, 1 / 3, 2, 1e-12 / 1.1, 5, 10])))
    assert b.log_error(rows, f) == pytest.approx(want)


def _rank_row(name, head_right: bool):
    """Two regions, the first truly 4× stronger; the head or the net ranks it first."""
    good, bad = (3.0, 1.0), (1.0, 3.0)
    h, n = (good, bad) if head_right else (bad, good)
    return {"map": name, "regions": [{"true": t, "seen": 1.0, "head": hh, "net": nn}
                                     for t, hh, nn in zip((4.0, 1.0), h, n)]}


def test_nested_choice_picks_the_weight_on_the_other_maps_only():
    """Maps a, b, c: the net ranks right (a = 1 wins there); map d: the head does. Left out,
    d gets the others' a = 1 and loses; each of a, b, c still sees two net-right maps."""
    b = _bench()
    rows = [_rank_row(m, False) for m in "abc"] + [_rank_row("d", True)]
    res = b.nested_choice(rows, grid=(0.0, 1.0), fixed=(0.0,))
    assert res["chosen"] == dict.fromkeys("abcd", 1.0)
    assert res["hits"] == {"nested": [3, 4], "a=0": [1, 4]}
    rows = [_rank_row(m, True) for m in "abc"] + [_rank_row("d", False)]
    res = b.nested_choice(rows, grid=(0.0, 1.0), fixed=(0.0,))
    assert res["chosen"] == dict.fromkeys("abcd", 0.0)
    assert res["hits"] == {"nested": [3, 4], "a=0": [3, 4]}
    # two maps that disagree: each is scored with the other's choice and misses (a choice
    # made on both maps would tie and hit one of them)
    res = b.nested_choice([_rank_row("a", False), _rank_row("b", True)], grid=(0.0, 1.0))
    assert res["chosen"] == {"a": 0.0, "b": 1.0} and res["hits"]["nested"] == [0, 2]
    with pytest.raises(ValueError, match="two maps"):
        b.nested_choice([_rank_row("a", True)])


def test_geometric_mix_is_between_head_and_net():
    b = _bench()
    r = {"true": 1.0, "seen": 1.0, "head": 16.0, "net": 1.0}
    p = b.predictors()
    assert p["geo 0.5"]([r])[0] == pytest.approx(4.0)
    assert p["geo 0.25"]([r])[0] == pytest.approx(8.0)
    assert p["head"]([r])[0] == 16.0 and p["net"]([r])[0] == 1.0


def test_relative_mix_keeps_a_lone_region_and_reorders_by_the_nets_relative_gain():
    b = _bench()
    f = b.predictors()["rel 1"]
    lone = {"true": 1.0, "seen": 1.0, "head": 30.0, "net": 1.5}
    assert f([lone])[0] == pytest.approx(30.0)           # no other region: the head's power
    a = {"true": 1.0, "seen": 1.0, "head": 20.0, "net": 8.0}     # net gain 8
    c = {"true": 1.0, "seen": 1.0, "head": 30.0, "net": 1.0}     # net gain 1
    got = f([a, c])                                      # × (8 / √8), × (1 / √8)
    assert got == pytest.approx([20.0 * 8 ** 0.5, 30.0 / 8 ** 0.5])
    assert np.argmax(got) == 0 and np.argmax(b.predictors()["head"]([a, c])) == 1


def test_share_predictor_is_what_add_lights_does():
    """The benchmark's ``share a`` gives the powers of ``lights.shared_power``."""
    from comgs_dr.lighting import lights as L
    b = _bench()
    h, w = 8, 16
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    lum = np.random.default_rng(1).uniform(1.0, 9.0, (h, w))
    regs, lobes = [], []
    for i, p in enumerate((2.0, 0.5, 7.0)):
        m = np.zeros((h, w), bool)
        m[2 * i:2 * i + 2, 3 * i:3 * i + 3] = True
        lobes.append({"region": m, "luminance_power": p})
        regs.append({"true": 1.0, "seen": 1.0, "head": p, "net": float((lum * dw * m).sum())})
    for a in b.SHARE:
        assert b.predictors()[f"share {a:g}"](regs) == pytest.approx(
            L.shared_power(lobes, lum, dw, a), rel=1e-12)


def _two_lamps(h, w):
    """A dim room with two 2×2-pixel lamps at opposite azimuths; the one at u ≈ 0 is 10× the
    other. Both clip white at EV 0."""
    img = np.full((h, w, 3), 0.05)
    img[h // 4:h // 4 + 2, 2:4] = 400.0
    img[h // 4:h // 4 + 2, w // 2 + 2:w // 2 + 4] = 40.0
    return img


def _full_masks(n, hh, ww, seed=0, **_):
    """A mask bank that sees the whole sphere (stands in for ``pano_masks.mask_bank``)."""
    d = equirect_directions(hh, ww)
    return [{"alpha": np.ones((hh, ww), np.float32), "normal": (-d).astype(np.float32),
             "coverage": 1.0} for _ in range(n)]


def _two_lamp_room(tmp_path, monkeypatch, h, w):
    """``room.exr`` (``_two_lamps``) in tmp_path, fully seen; the benchmark importable."""
    from comgs_dr.data import pano_masks
    from comgs_dr.lighting.envmap import write_exr
    monkeypatch.setattr(pano_masks, "mask_bank", _full_masks)
    monkeypatch.syspath_prepend(str(BENCHMARKS))     # it imports lighting_eval
    write_exr(tmp_path / "room.exr", _two_lamps(h, w), "equirect")
    return tmp_path / "room.exr"


def test_region_powers_finds_both_lamps_and_their_true_order(tmp_path, variant, monkeypatch):
    from comgs_dr.lighting import lights
    from comgs_dr.lighting.backends import DEFAULT_WEIGHTS
    if not (Path(DEFAULT_WEIGHTS).is_file() and lights.DEFAULT_HEAD.is_file()):
        pytest.skip("shipped weights missing")
    h, w = 32, 64
    _two_lamp_room(tmp_path, monkeypatch, h, w)
    b = _bench()
    rows = b.region_powers([tmp_path / "room.exr"], masks=2, seed=0, res=h, progress=lambda s: 0)
    assert len(rows) == 2
    for row in rows:
        regs = row["regions"]
        assert len(regs) == 2
        t = np.array([r["true"] for r in regs])
        assert t.max() / t.min() == pytest.approx(10.0, rel=0.2)   # the lamps' true ratio
        for r in regs:
            assert all(np.isfinite(r[k]) and r[k] > 0 for k in ("seen", "head", "net"))
            assert r["head"] >= r["seen"] * (1 - 1e-9)             # the head's gain is ≥ 1
    _, n, _ = b.score(rows, b.predictors()["seen"], 1.5)
    assert n == 2                                             # both panoramas pass the margin


def test_region_powers_scores_each_map_with_its_cv_head(tmp_path, variant, monkeypatch):
    """``--cv-heads``: the map's own fold is the head that predicts (a constant-gain head
    here: every region gets exactly 5× its EV-0 power), not the shipped one."""
    import math

    import torch

    from comgs_dr.lighting import lights
    from comgs_dr.lighting.backends import DEFAULT_WEIGHTS
    if not Path(DEFAULT_WEIGHTS).is_file():
        pytest.skip("shipped completion weights missing")
    h, w = 32, 64
    _two_lamp_room(tmp_path, monkeypatch, h, w)
    head = lights.LightHead(hidden=8)
    with torch.no_grad():
        for p in head.parameters():
            p.zero_()
        head.mlp[-1].bias.fill_(math.log(math.expm1(math.log(5.0))))   # softplus⁻¹(log 5)
    cv = lights.save_head(head, tmp_path / "cv" / "room.pt")
    b = _bench()
    rows = b.region_powers([tmp_path / "room.exr"], masks=1, seed=0, res=h,
                           progress=lambda s: 0, cv_heads={"room": cv})
    regs = rows[0]["regions"]
    assert len(regs) == 2
    for r in regs:
        assert r["head"] == pytest.approx(5.0 * r["seen"], rel=1e-4)
    with pytest.raises(SystemExit, match="replaces --light-head"):
        b.main(["--cv-heads", str(tmp_path / "cv"), "--light-head", str(cv)])
