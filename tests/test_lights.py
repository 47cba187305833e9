"""Light lobes and the light head (lighting.lights): SG integrals, exact lobe power, clipped
regions, features on extreme inputs, re-adding missing power, weights files."""
import numpy as np
import pytest
import torch

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles
from comgs_dr.lighting import lights as L
from comgs_dr.lighting.hdr import expose


def _dw(h, w):
    return np.broadcast_to(pixel_solid_angles(h, w), (h, w))


@pytest.mark.parametrize("lam", [1e-3, 0.3, 2.0, 40.0, 900.0])
def test_sg_integral_matches_quadrature_and_inverts(lam):
    h, w = 512, 1024
    d = equirect_directions(h, w)
    g = np.exp(lam * (d[..., 2] - 1.0))                      # axis +Z
    quad = float((g * _dw(h, w)).sum())
    assert float(L.sg_integral(lam)) == pytest.approx(quad, rel=2e-3)
    assert float(L.sg_sharpness(L.sg_integral(lam))) == pytest.approx(lam, rel=1e-6)


def test_sg_sharpness_rejects_impossible_solid_angles():
    for om in (0.0, -1.0, 4 * np.pi, np.nan):
        with pytest.raises(ValueError, match="solid angles"):
            L.sg_sharpness(om)


@pytest.mark.parametrize("lam", [0.5, 50.0, 1e7])          # 1e7: far narrower than a pixel
def test_render_lobes_keeps_power(lam):
    h, w = 32, 64
    d = np.array([0.3, -0.5, 0.8])
    power = np.array([3.0, 2.0, 1e6])
    img = L.render_lobes([{"direction": d, "sharpness": lam, "rgb_power": power}], h, w)
    assert np.isfinite(img).all() and img.min() >= 0
    np.testing.assert_allclose((img * _dw(h, w)[..., None]).sum((0, 1)), power, rtol=1e-9)
    peak = np.unravel_index(np.argmax(img[..., 0]), (h, w))
    assert equirect_directions(h, w)[peak] @ (d / np.linalg.norm(d)) > 0.97


def _sun_map(h=64, w=128, sun=(0.6, 0.2, 0.35), radiance=5e4):
    d = equirect_directions(h, w)
    img = 0.3 + 0.5 * np.clip(d[..., 2:], 0, 1) * np.array([0.5, 0.7, 1.0])
    s = np.asarray(sun) / np.linalg.norm(sun)
    img[d @ s > np.cos(np.radians(3.0))] = radiance
    return img, s


def test_clipped_regions_find_the_sun_and_ignore_unobserved_pixels():
    img, s = _sun_map()
    ldr = expose(img, 0.0)
    mask = np.ones(img.shape[:2])
    regions = L.clipped_regions(ldr, mask)
    assert len(regions) == 1
    assert regions[0].direction @ s > np.cos(np.radians(2.0))
    assert regions[0].seen_power @ LUMA == pytest.approx(regions[0].solid_angle, rel=1e-6)
    hole = mask * (equirect_directions(64, 128) @ s < 0.9)   # the sun unobserved
    assert L.clipped_regions(ldr, hole) == []


def test_clipped_region_across_the_seam_is_one():
    h, w = 32, 64
    ldr = np.full((h, w, 3), 0.3)
    ldr[10:13, :2] = 1.0
    ldr[10:13, -2:] = 1.0
    regions = L.clipped_regions(ldr, np.ones((h, w)))
    assert len(regions) == 1 and regions[0].pixels.sum() == 12
    assert abs(regions[0].direction[1]) < 1e-9 and regions[0].direction[0] < 0   # u = 0 is -X


def test_regions_clipped_in_one_channel_only_are_not_lights():
    h, w = 32, 64
    ldr = np.full((h, w, 3), 0.3)
    ldr[5:7, 10:12] = [0.6, 0.8, 1.0]                  # a saturated blue speck
    ldr[20:22, 40:42] = [1.0, 0.9, 0.5]                # orange, clipped in red only...
    ldr[21, 41] = 1.0                                  # ...with a white core
    regions = L.clipped_regions(ldr, np.ones((h, w)))
    assert len(regions) == 1 and regions[0].pixels[20:22, 40:42].all()
    assert len(L.clipped_regions(ldr, np.ones((h, w)), white_core=False)) == 2


@pytest.mark.parametrize("case", ["all_clipped", "one_pixel_at_pole", "no_ring", "black"])
def test_features_are_finite_on_extreme_panoramas(case):
    h, w = 32, 64
    ldr, mask = np.full((h, w, 3), 0.4), np.ones((h, w))
    if case == "all_clipped":
        ldr[:] = 1.0
    elif case == "one_pixel_at_pole":
        ldr[0, 5] = 1.0
    elif case == "no_ring":
        ldr[12:14, 20:22] = 1.0
        mask[8:18, 14:28] = 0.0
        mask[12:14, 20:22] = 1.0
    else:
        ldr[:] = 0.0
        ldr[3, 3] = 1.0
    regions = L.clipped_regions(ldr, mask)
    assert regions
    f = L.region_features(ldr, mask, regions, label=1)
    assert f.shape == (len(regions), len(L.FEATURES)) and np.isfinite(f).all()
    lobes = L.predict_lobes(ldr, mask, L.LightHead().eval(), label=1)
    out, added = L.add_lights(expose_back(ldr), lobes)
    assert np.isfinite(out).all()


def expose_back(ldr):
    from comgs_dr.lighting.hdr import unexpose
    return unexpose(ldr, 0.0)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="NaN"):
        L.clipped_regions(np.full((8, 16, 3), np.nan), np.ones((8, 16)))
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        L.clipped_regions(np.ones((8, 16)), np.ones((8, 16)))
    with pytest.raises(ValueError, match="finite"):
        L.add_lights(np.full((8, 16, 3), np.inf), [])


class _Gain(torch.nn.Module):
    """A head that answers a fixed log gain (to test add_lights' bookkeeping)."""

    def __init__(self, g):
        super().__init__()
        self.g = g

    def forward(self, x):
        return torch.full((len(x),), float(self.g))


def test_add_lights_restores_the_predicted_power():
    img, s = _sun_map(radiance=5e4)
    ldr = expose(img, 0.0)
    mask = np.ones(img.shape[:2])
    fused = expose_back(ldr)                                  # the sun clipped at 1
    dw = _dw(*img.shape[:2])
    true_p = float(((img @ LUMA) * dw)[ldr.max(-1) >= L.SAT].sum())
    seen_p = float(((fused @ LUMA) * dw)[ldr.max(-1) >= L.SAT].sum())
    lobes = L.predict_lobes(ldr, mask, _Gain(np.log(true_p / seen_p)))
    assert lobes[0]["luminance_power"] == pytest.approx(true_p, rel=1e-5)
    out, added = L.add_lights(fused, lobes)
    total = float(((out @ LUMA) * dw).sum())
    assert total == pytest.approx(float(((img @ LUMA) * dw).sum()), rel=1e-4)
    assert added[0]["direction"] @ s > np.cos(np.radians(2.0))
    half = {**lobes[0], "luminance_power": 0.5 * true_p}
    out2, added2 = L.add_lights(out, [half], excess="keep")
    assert added2 == [] and np.array_equal(out2, out)         # "keep" never removes light
    # "match": the excess over the white level inside the region is scaled to the head's power
    out3, added3 = L.add_lights(out, [half])
    reg = lobes[0]["region"]
    assert added3 == []
    assert float(((out3 @ LUMA) * dw)[reg].sum()) == pytest.approx(0.5 * true_p, rel=1e-6)
    assert np.array_equal(out3[~reg], out[~reg])              # nothing outside the region
    assert (out3[reg] >= np.minimum(out[reg], 1.0) - 1e-12).all()   # never below white
    # a target below what the white level alone holds: the region stays at the white level
    out4, _ = L.add_lights(out, [{**lobes[0], "luminance_power": 1e-9}])
    assert np.allclose(out4[reg], np.minimum(out[reg], 1.0))
    with pytest.raises(ValueError, match="excess"):
        L.add_lights(out, [half], excess="drop")
    # describe_regions: every region with what happened there, including the matched one
    d1, = L.describe_regions(lobes, fused, out)
    assert d1["action"] == "added" and d1["power"] == pytest.approx(true_p, rel=1e-4)
    assert d1["brackets_power"] == pytest.approx(seen_p, rel=1e-6)
    assert d1["predicted_power"] == pytest.approx(true_p, rel=1e-5)
    d3, = L.describe_regions([half], out, out3)
    assert d3["action"] == "reduced" and d3["power"] == pytest.approx(0.5 * true_p, rel=1e-6)
    d2, = L.describe_regions([half], out, out2)
    assert d2["action"] == "unchanged" and d2["power"] == d2["brackets_power"]
    # as estimate_light calls it: float32 maps, the untouched region bit-identical
    d4, = L.describe_regions([half], out.astype(np.float32), out2.astype(np.float32))
    assert d4["action"] == "unchanged"
    d5, = L.describe_regions(lobes, fused.astype(np.float32), out.astype(np.float32))
    assert d5["action"] == "added" and d5["solid_angle"] == lobes[0]["solid_angle"]


def _two_regions(h=32, w=64, level=8.0):
    """A fused map with two disjoint 2×2 regions: the brackets hold ``level`` (region a) and
    1 (region b) per pixel; lobes whose predicted powers favour b 3 : 2. The predictions
    (2, 3) are far above what the pixels hold at level 8 (the missing power is added) and far
    below it at level 1e5 (region a's excess is matched down)."""
    fused = np.full((h, w, 3), 0.1)
    ra, rb = np.zeros((h, w), bool), np.zeros((h, w), bool)
    ra[8:10, 4:6], rb[8:10, 36:38] = True, True
    fused[ra], fused[rb] = level, 1.0
    lobes = [{"region": r, "luminance_power": p, "direction": np.array([0.0, 0.0, 1.0]),
              "sharpness": 1.0, "solid_angle": 0.01, "colour": np.ones(3), "gain": 1.0}
             for r, p in ((ra, 2.0), (rb, 3.0))]
    return fused, lobes


@pytest.mark.parametrize("level", [8.0, 1e5])
@pytest.mark.parametrize("a", [0.0, 0.25, 0.5, 1.0])
def test_bracket_vote_shares_the_heads_total_power(a, level):
    """trust_brackets = a: the head's total (5) is kept and shared ∝ P^(1−a)·B^a, B the
    brackets' power in the region; a = 0 or a lone region: the head's powers unchanged.
    The map ends with each region at its share, whether power is added or matched down."""
    fused, lobes = _two_regions(level=level)
    dw = _dw(*fused.shape[:2])
    lum = fused @ LUMA
    b = np.array([float((lum * dw * lb["region"]).sum()) for lb in lobes])  # B_a = 8 B_b
    got = L.shared_power(lobes, lum, dw, a)
    w = np.array([2.0, 3.0]) ** (1 - a) * b ** a
    assert got == pytest.approx(5.0 * w / w.sum(), rel=1e-12)
    assert got.sum() == pytest.approx(5.0, rel=1e-12)
    assert (got[0] > got[1]) == (a >= 0.25)                   # 2^.75·8^.25 > 3^.75 (a = ¼)
    assert L.shared_power(lobes[:1], lum, dw, a) == pytest.approx([2.0])
    out, _ = L.add_lights(fused, lobes, trust_brackets=a)
    have = [float(((out @ LUMA) * dw)[lb["region"]].sum()) for lb in lobes]
    floor = [float(((np.minimum(fused, 1.0) @ LUMA) * dw)[lb["region"]].sum()) for lb in lobes]
    assert have == pytest.approx(list(np.maximum(got, floor)), rel=1e-6)   # never below white
    assert (np.maximum(got, floor) == got).all() or (level > 100 and a > 0.25)
    desc = L.describe_regions(lobes, fused, out, trust_brackets=a)
    assert [g["voted_power"] for g in desc] == pytest.approx(list(got), rel=1e-12)
    assert [g["predicted_power"] for g in desc] == [2.0, 3.0]
    want = ["added" if g > bb else "reduced" if bb > f else "unchanged"
            for g, bb, f in zip(got, b, floor)]
    assert [g["action"] for g in desc] == want
    assert (want[0] == "reduced") == (level > 100)            # the branch the case is for


def test_bracket_vote_default_and_bad_values():
    fused, lobes = _two_regions()
    ref, _ = L.add_lights(fused, lobes)                        # the default (TRUST_BRACKETS)
    ref_a, _ = L.add_lights(fused, lobes, trust_brackets=L.TRUST_BRACKETS)
    assert np.array_equal(ref, ref_a) and 0.0 < L.TRUST_BRACKETS < 1.0
    dw = _dw(*fused.shape[:2])
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="trust_brackets"):
            L.add_lights(fused, lobes, trust_brackets=bad)
        with pytest.raises(ValueError, match="trust_brackets"):
            L.shared_power(lobes, fused @ LUMA, dw, bad)
        with pytest.raises(ValueError, match="trust_brackets"):
            L.describe_regions(lobes, fused, fused, trust_brackets=bad)


def test_dominance_is_the_strongest_over_the_next():
    assert L.dominance([]) is None and L.dominance([{"power": 3.0}]) is None
    assert L.dominance([{"power": 1.0}, {"power": 4.0}, {"power": 2.0}]) == 2.0
    assert L.dominance([{"power": 1.0}, {"power": 0.0}]) is None     # no second light


def test_head_weights_round_trip_and_errors(tmp_path):
    head = L.LightHead()
    torch.nn.init.normal_(head.mlp[0].weight)
    p = L.save_head(head, tmp_path / "h.pt", {"note": 1})
    back = L.load_head(p)
    x = torch.randn(5, len(L.FEATURES))
    assert torch.equal(back(x), head.eval()(x))
    with pytest.raises(FileNotFoundError):
        L.load_head(tmp_path / "missing.pt")
    (tmp_path / "bad.pt").write_bytes(b"not torch")
    with pytest.raises(ValueError, match="not a readable"):
        L.load_head(tmp_path / "bad.pt")


def test_context_features_rank_the_regions_by_seen_power():
    """The last three features: log seen power minus the largest, rank (0 = largest), log
    share; equal for equal lamps, and a region alone has 0, 0, 0."""
    img, s = _sun_map(radiance=50.0)
    d = equirect_directions(64, 128)
    for axis, cap in (((-0.6, 0.3, 0.4), 6.0), ((0.1, -0.7, 0.3), 4.0)):   # two smaller lamps
        a = np.asarray(axis) / np.linalg.norm(axis)
        img[d @ a > np.cos(np.radians(cap))] = 50.0
    ldr, mask = expose(img, 0.0), np.ones((64, 128))
    regions = L.clipped_regions(ldr, mask)
    assert len(regions) == 3
    ctx = L.region_features(ldr, mask, regions)[:, -3:]
    seen = np.array([r.seen_power @ LUMA for r in regions])
    np.testing.assert_allclose(ctx[:, 0], np.log(seen / seen.max()), atol=1e-5)
    assert list(ctx[:, 1]) == list(np.argsort(np.argsort(-seen)))
    np.testing.assert_allclose(np.exp(ctx[:, 2]).sum(), 1.0, rtol=1e-5)
    alone = L.region_features(ldr, mask, regions[:1])[:, -3:]
    np.testing.assert_allclose(alone, 0.0, atol=1e-6)


def test_a_head_fitted_before_the_context_features_reads_its_prefix(tmp_path):
    """FEATURES only grows at its end: a head of the first N_BASE_FEATURES saves that list,
    loads, and gives the same output on full feature rows as on its prefix."""
    torch.manual_seed(0)
    old = L.LightHead(L.N_BASE_FEATURES)
    torch.nn.init.normal_(old.mlp[0].weight)
    x = torch.randn(4, len(L.FEATURES))
    back = L.load_head(L.save_head(old, tmp_path / "old.pt"))
    assert back.n_features == L.N_BASE_FEATURES
    assert torch.equal(back(x), old.eval()(x[:, :L.N_BASE_FEATURES]))
    ck = torch.load(tmp_path / "old.pt", weights_only=True)
    ck["features"] = ["log_solid_angle", "something_else"]
    torch.save(ck, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other features"):
        L.load_head(tmp_path / "other.pt")


def test_head_ensemble_is_the_mean_log_gain_and_round_trips(tmp_path):
    torch.manual_seed(3)
    heads = [L.LightHead() for _ in range(3)]
    for h in heads:
        torch.nn.init.normal_(h.mlp[0].weight)
    ens = L.HeadEnsemble(heads).eval()
    x = torch.randn(7, len(L.FEATURES))
    ref = torch.stack([h.eval()(x) for h in heads]).mean(0)
    torch.testing.assert_close(ens(x), ref)
    back = L.load_head(L.save_head(ens, tmp_path / "e.pt"))
    assert isinstance(back, L.HeadEnsemble) and len(back.heads) == 3
    torch.testing.assert_close(back(x), ref)
    img, _ = _sun_map()
    lobes = L.predict_lobes(expose(img * 0.05, 0.0), np.ones((64, 128)), back, 1)
    assert lobes and all(np.isfinite(lb["gain"]) and lb["gain"] >= 1 for lb in lobes)
    with pytest.raises(ValueError):
        L.HeadEnsemble([])


def test_training_targets_are_the_true_power_ratio():
    """_draws: a full view of a map with a 5e4 sun gives target log(P_true / P_seen)."""
    from comgs_dr.stages.train_light_head import TrainLightHeadConfig, _draws
    img, s = _sun_map(radiance=5e4)
    cfg = TrainLightHeadConfig(aug_ev=0.0, wb_jitter=0.0, full_view=1.0, blur_frac=0.0)
    feats, targets, groups, panos, seen = [], [], [], [], []
    _draws(np.random.default_rng(0), img, np.ones((1, 64, 128)), 3, cfg, 0, 7, feats, targets,
           groups, panos, seen)
    assert len(targets) >= 3 and groups[0] == 7
    assert len(panos) == len(seen) == len(targets) and panos[0] == 0 and panos[-1] == 2
    assert np.all(np.diff(panos) >= 0)                 # one running index per panorama
    from comgs_dr.lighting.pano_data import auto_exposure
    k = auto_exposure(img)
    sun = float((((img * k) @ LUMA) * _dw(64, 128))[img[..., 0] > 1e3].sum())
    seen = float(_dw(64, 128)[img[..., 0] > 1e3].sum())      # clipped at the white level 1
    assert max(targets) == pytest.approx(np.log(sun / seen), rel=0.05)


def test_rank_loss_matches_per_panorama_softmax_and_its_gradient():
    """_rank_loss (scatter form) = the mean over panoramas of the cross-entropy of
    softmax(true log powers) and log softmax(predicted), checked against a loop; its gradient
    against central differences; finite for powers far apart (e^±80)."""
    from comgs_dr.stages.train_light_head import _rank_loss
    g = torch.Generator().manual_seed(0)
    pred = torch.randn(9, generator=g, dtype=torch.float64)
    y, ls = torch.randn(9, generator=g, dtype=torch.float64), torch.randn(9, generator=g)
    seg = torch.tensor([0, 0, 0, 1, 1, 2, 2, 2, 2])
    ref = sum(-(torch.softmax((ls + y)[seg == b], 0)
                * torch.log_softmax((ls + pred)[seg == b], 0)).sum() for b in range(3)) / 3
    p = pred.clone().requires_grad_()
    loss = _rank_loss(p, y, ls.double(), seg)
    assert float(loss.detach()) == pytest.approx(float(ref), rel=1e-12)
    loss.backward()
    eps = 1e-6
    for i in range(9):
        d = torch.zeros(9, dtype=torch.float64)
        d[i] = eps
        fd = (_rank_loss(pred + d, y, ls.double(), seg)
              - _rank_loss(pred - d, y, ls.double(), seg)) / (2 * eps)
        assert float(p.grad[i]) == pytest.approx(float(fd), abs=1e-7)
    far = _rank_loss(torch.tensor([80.0, -80.0]), torch.tensor([-80.0, 80.0]),
                     torch.zeros(2), torch.tensor([0, 0]))
    assert torch.isfinite(far) and float(far) > 100     # the wrong region first: large loss


def test_pano_sampler_and_top1():
    from comgs_dr.stages.train_light_head import _PanoSampler, top1
    panos = np.array([0, 0, 1, 2, 2, 2, 3, 4, 4])
    sm = _PanoSampler(panos, 0)
    for _ in range(20):
        idx, seg = sm.sample(2)
        idx, seg = idx.numpy(), seg.numpy()
        for b in np.unique(seg):                  # whole panoramas of ≥ 2 regions each
            p = np.unique(panos[idx[seg == b]])
            assert len(p) == 1 and p[0] in (0, 2, 4)
            assert (seg == b).sum() == (panos == p[0]).sum()
    assert not _PanoSampler(np.array([0, 1, 2]), 0)          # no panorama with two regions
    truth = np.array([1.0, 2.0, 5.0, 0.0, 3.0, 1.0, 9.0, 4.0, 3.0])
    score = np.array([3.0, 2.0, 0.0, 1.0, 0.0, 2.0, 0.0, 1.0, 2.0])
    # panoramas 0, 2, 4 have two or more regions; the score picks the true top in none
    assert top1(score, truth, panos) == (0.0, 3)
    assert top1(truth, truth, panos) == (1.0, 3)


def test_room_resize_round_trip_and_bad_sizes():
    from comgs_dr.stages.train_light_head import _resize_rows
    img = np.random.default_rng(0).random((16, 32, 3))
    up = _resize_rows(img, 64)
    assert up.shape == (64, 128, 3)
    np.testing.assert_allclose(_resize_rows(up, 16), img, rtol=1e-12)
    dw16, dw8 = _dw(16, 32), _dw(8, 16)
    np.testing.assert_allclose((_resize_rows(img, 8) * dw8[..., None]).sum((0, 1)),
                               (img * dw16[..., None]).sum((0, 1)), rtol=1e-9)   # power kept
    with pytest.raises(ValueError):
        _resize_rows(img, 24)


def test_train_light_head_tiny_run(tmp_path):
    from comgs_dr.lighting.envmap import write_exr
    from comgs_dr.stages.train_light_head import TrainLightHeadConfig, train
    maps = tmp_path / "maps"
    for name, sun in (("yard", (0.6, 0.2, 0.35)), ("held", (-0.2, 0.5, 0.4))):
        write_exr(maps / f"{name}.exr", _sun_map(sun=sun)[0].astype(np.float32), "equirect")
    cfg = TrainLightHeadConfig(out=tmp_path / "head.pt", data_dir=tmp_path / "data",
                               maps_dir=maps, held_out=("held",), heights=(64,), draws_real=6,
                               n_sky=2, draws_sky=2, n_rooms=1, draws_room=1, n_masks=4,
                               steps=30)
    info = train(cfg, progress=False, command="test")
    assert info["maps"] == ["yard"] and info["regions"] > 0
    head = L.load_head(cfg.out)
    assert np.isfinite(info["history"][-1]["train_huber"])
    assert [r["left_out"] for r in info["cross_validation"]][:1] == ["yard"]
    assert all(np.isfinite(r["mae_log"]) for r in info["cross_validation"])
    img, _ = _sun_map()
    lobes = L.predict_lobes(expose(img * 0.05, 0.0), np.ones((64, 128)), head, 0)
    assert lobes and all(np.isfinite(lb["gain"]) and lb["gain"] >= 1 for lb in lobes)
    from dataclasses import replace
    ens_cfg = replace(cfg, out=tmp_path / "ens.pt", ensemble=3, cv=False)
    info2 = train(ens_cfg, progress=False, command="test")              # the cached data
    assert info2["data_seconds"] == info["data_seconds"]
    ens = L.load_head(ens_cfg.out)
    assert isinstance(ens, L.HeadEnsemble) and len(ens.heads) == 3
    x = torch.from_numpy(L.region_features(expose(img * 0.05, 0.0), np.ones((64, 128)),
                                           L.clipped_regions(expose(img * 0.05, 0.0),
                                                             np.ones((64, 128))), 0))
    torch.testing.assert_close(ens(x), torch.stack([h(x) for h in ens.heads]).mean(0))
    torch.testing.assert_close(ens.heads[0](x), head(x))                 # member 0 = seed 0
    # --cv-out: the left-out map's fold head, whose card does not list that map
    from comgs_dr.lighting.pano_data import trained_maps
    from comgs_dr.stages.train_light_head import cross_validate
    d = np.load(cfg.data_dir / "light_head_data.npz")
    x, y = torch.from_numpy(d["features"]), torch.from_numpy(d["targets"])
    cv = cross_validate(x, y, d["groups"], d["names"], cfg, tmp_path / "cv")
    assert sorted(p.name for p in (tmp_path / "cv").iterdir()) == ["yard.json", "yard.pt"]
    assert trained_maps(tmp_path / "cv" / "yard.pt") == frozenset()
    fold = L.load_head(tmp_path / "cv" / "yard.pt")
    te = torch.from_numpy(d["groups"] == 0)
    with torch.no_grad():
        assert abs(float((fold(x[te]) - y[te]).abs().mean()) - cv[0]["mae_log"]) < 1e-3
    cross_validate(x, y, d["groups"], d["names"], replace(cfg, ensemble=2), tmp_path / "cv2")
    fold2 = L.load_head(tmp_path / "cv2" / "yard.pt")          # the folds fit what ships
    assert isinstance(fold2, L.HeadEnsemble) and len(fold2.heads) == 2
    torch.testing.assert_close(fold2.heads[0](x), fold(x))
    # the CV rows score "strongest region first"; the listwise loss needs the panoramas
    assert {"top1", "top1_seen", "panoramas"} <= set(info["cross_validation"][0])
    from comgs_dr.stages.train_light_head import fit_head
    with pytest.raises(ValueError, match="panorama"):
        fit_head(x, y, replace(cfg, rank_weight=1.0))
    ranked = train(replace(cfg, out=tmp_path / "rank.pt", rank_weight=1.0, cv=False),
                   progress=False, command="test")
    assert np.isfinite(ranked["history"][-1]["train_huber"])
    assert L.load_head(tmp_path / "rank.pt").n_features == len(L.FEATURES)


def test_scene_probe_is_the_maps_light_inside_the_composition_scene(tmp_path):
    """``scene_probe``: the light at a placement in the procedural scene; above the horizon
    mostly the (turned) map, below it the scene's ground instead of the map's."""
    from comgs_dr.data.composition_dataset import write_textures
    from comgs_dr.stages.train_light_head import scene_probe
    img, _ = _sun_map()
    img = img.astype(np.float32)
    img[32:] = 5.0                                   # a bright "ground" in the map itself
    pr = scene_probe(img, np.random.default_rng(0), write_textures(tmp_path / "tex"),
                     height=32, spp_side=2)
    assert pr.shape == (32, 64, 3) and np.isfinite(pr).all() and pr.min() >= 0
    low = pr[28:]                                    # the scene's textured, sunlit ground
    assert abs(low.mean() - 5.0) > 1.0 and low.std() > 0.05 * low.mean()
    assert pr.max() > 10.0                           # the sun is still in view above


def test_train_light_head_with_scene_probes(tmp_path):
    from comgs_dr.lighting.envmap import write_exr
    from comgs_dr.stages.train_light_head import TrainLightHeadConfig, build_data
    maps = tmp_path / "maps"
    write_exr(maps / "yard.exr", _sun_map(sun=(0.6, 0.2, 0.35))[0].astype(np.float32),
              "equirect")
    base = dict(out=tmp_path / "head.pt", maps_dir=maps, held_out=(), heights=(64,),
                draws_real=2, n_sky=1, draws_sky=1, n_rooms=1, draws_room=1, n_masks=2)
    plain = build_data(TrainLightHeadConfig(data_dir=tmp_path / "a", **base), progress=False)
    more = build_data(TrainLightHeadConfig(data_dir=tmp_path / "b", scene_probes=1,
                                           draws_scene=3, **base), progress=False)
    # the scene probe's draws are the map's (group 0, left out with it in the CV)
    assert (more["groups"] == 0).sum() > (plain["groups"] == 0).sum()


def test_shipped_head_recovers_unseen_suns():
    """The shipped head on Mitsuba sunsky skies it never saw (seeds unused in training), fully
    observed at 64x128: the sun region's predicted power against the true one, and against
    what the EV-0 pixels hold."""
    import json

    from comgs_dr.lighting import pano_data as P
    rec = json.loads(L.DEFAULT_HEAD.with_suffix(".json").read_text())
    assert not set(rec["held_out"]) & set(rec["maps"]) and rec["cross_validation"]
    head = L.load_head()
    rng = np.random.default_rng(987654)
    dw = _dw(64, 128)
    err_head, err_seen = [], []
    while len(err_head) < 8:
        sky = P.sunsky_panorama(rng, 64, 128).astype(np.float64)
        sky *= P.auto_exposure(sky)
        ldr = expose(sky, 0.0)
        lobes = L.predict_lobes(ldr, np.ones((64, 128)), head, 0)
        if not lobes:
            continue
        lb = lobes[0]
        true = float(((sky @ LUMA) * dw * lb["region"]).sum())
        seen = lb["luminance_power"] / lb["gain"]
        if true < 3 * seen:                                   # no clipped sun (overcast)
            continue
        err_head.append(abs(np.log(lb["luminance_power"] / true)))
        err_seen.append(abs(np.log(seen / true)))
    print("median |log| error: head", np.median(err_head), "EV-0 pixels", np.median(err_seen))
    assert np.median(err_head) < np.log(1.6) and np.median(err_head) < 0.25 * np.median(err_seen)


def test_blur_ldr_keeps_flat_regions_and_the_mask_and_softens_a_sun():
    from comgs_dr.stages.train_light_head import blur_ldr
    img, s = _sun_map()
    ldr = expose(img, 0.0)
    h, w = ldr.shape[:2]
    mask = np.ones((h, w))
    mask[:, : w // 4] = 0.0
    ldr = np.where(mask[..., None] > 0.5, ldr, 0.0)
    out = blur_ldr(ldr, mask, 2.0)
    assert np.all(out[:, : w // 4] == 0) and np.isfinite(out).all()
    flat = np.full((h, w, 3), 0.4)
    assert np.allclose(blur_ldr(flat, mask, 2.0)[:, w // 4:], 0.4, atol=1e-9)  # no dark rim
    white = lambda x: (x.min(-1) >= L.SAT).sum()                               # noqa: E731
    clipped = lambda x: (x.max(-1) >= L.SAT).sum()                             # noqa: E731
    assert white(out) / max(clipped(out), 1) <= white(ldr) / max(clipped(ldr), 1)


def test_downsample_clipped_keeps_lights_that_fill_their_block():
    """Blocks are averaged, except that a block at least ¾ clipped (observed) takes its
    brightest clipped pixel and counts as observed; f = 1 is the identity; f must divide."""
    rng = np.random.default_rng(0)
    ldr = rng.uniform(0.1, 0.6, (8, 16, 3))
    mask = np.ones((8, 16))
    mask[:, :4] = 0.0
    ldr[2:4, 8:10] = [1.0, 1.0, 0.7]                              # a sun filling a block
    ldr[3, 9] = [0.5, 0.5, 0.5]                                   # ... all but one pixel
    ldr[2, 8] = [1.0, 1.0, 1.0]                                   # its brightest pixel
    ldr[6, 12] = 1.0                                              # a lone clipped pixel
    ldr[4:6, 0:2] = 1.0                                           # clipped but unobserved
    out, m = L.downsample_clipped(ldr, mask, 2)
    assert out.shape == (4, 8, 3) and m.shape == (4, 8)
    np.testing.assert_allclose(out[1, 4], 1.0)
    assert m[1, 4] == 1.0
    np.testing.assert_allclose(out[3, 6], ldr[6:8, 12:14].reshape(-1, 3).mean(0))
    assert out[2, 0].max() == 1.0 and m[2, 0] == 0.0              # unobserved: averaged
    regs = L.clipped_regions(out, m)
    assert len(regs) == 1 and regs[0].pixels[1, 4]
    any_px, _ = L.downsample_clipped(ldr, mask, 2, fraction=0.0)  # any clipped pixel
    np.testing.assert_allclose(any_px[3, 6], 1.0)
    same, _ = L.downsample_clipped(ldr, mask, 1)
    np.testing.assert_array_equal(same, np.clip(ldr, 0, 1))
    with pytest.raises(ValueError, match="divide"):
        L.downsample_clipped(ldr, mask, 3)


def test_held_out_maps_get_the_shipped_heads_fold_without_them():
    """The shipped head saw every shared map; the benchmarks score a held-out map with its
    cross-validation fold (``benchmarks/cv_heads.py``), whose card lacks that map, and which
    predicts finite gains."""
    from bench_module import load_benchmark

    from comgs_dr.lighting.pano_data import HELD_OUT, trained_maps
    cv = load_benchmark("cv_heads")
    card = trained_maps(L.DEFAULT_HEAD)
    for stem in HELD_OUT:
        path = cv.held_out_head(stem)
        assert path == cv.CV_HEADS / f"{stem}.pt" and stem not in trained_maps(path)
        assert trained_maps(path) == card - {stem}
        assert cv.held_out_head(stem, "mine.pt") == "mine.pt"    # a given head is kept
    assert cv.held_out_head("blender_city") == "default"         # no fold kept for it
    x = torch.zeros(1, len(L.FEATURES))                           # "default" loads the shipped
    torch.testing.assert_close(L.load_head("default")(x), L.load_head(L.DEFAULT_HEAD)(x))
    assert cv.held_out_head("blender_city", None) is None
    img, _ = _sun_map()
    ldr = expose(img * 0.05, 0.0)
    lobes = L.predict_lobes(ldr, np.ones((64, 128)), L.load_head(cv.held_out_head(HELD_OUT[0])), 0)
    assert lobes and all(np.isfinite(lb["gain"]) and lb["gain"] >= 1 for lb in lobes)
