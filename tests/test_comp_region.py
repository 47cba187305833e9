"""Scores and figures of the object+shadow region (eval.comp_region) on images whose
answers are known by construction."""
import numpy as np
import pytest

from comgs_dr.core.colorspace import srgb_encode
from comgs_dr.eval import comp_region as cr


def _frame(depth=0.4, colour=(0.5, 0.25, 0.1), h=48, w=64):
    """Empty scene (grey 0.3 linear), the truth with an object square and a shadow band
    beside it darkened to ``depth``; returns (empty_lin, gt_srgb, obj, shadow_true)."""
    empty = np.full((h, w, 3), 0.3)
    obj = np.zeros((h, w), bool)
    obj[10:20, 10:20] = True
    shadow = np.zeros((h, w), bool)
    shadow[22:30, 8:50] = True
    gt = empty.copy()
    gt[shadow] *= depth
    gt[obj] = colour
    return empty, srgb_encode(gt), obj, shadow


def test_region_scores_recover_known_darkness_and_colour():
    empty, gt, obj, shadow = _frame(depth=0.4)
    sh, region, _ = cr.regions(np.asarray(cr.srgb_decode(gt)), empty, obj)
    assert (sh == shadow).all()
    assert region[obj].all() and region[shadow].all() and region.sum() < 0.5 * region.size
    # ours: the shadow half as deep (0.7), the object 20 % redder, rest exact
    _, ours, _, _ = _frame(depth=0.7, colour=(0.6, 0.25, 0.1))
    s = cr.summarise([cr.frame_scores(ours, gt, empty, obj)])
    assert s["shadow_ratio_truth"] == pytest.approx(0.4, abs=0.01)
    assert s["shadow_ratio"] == pytest.approx(0.7, abs=0.01)
    assert s["shadow_depth"] == pytest.approx(0.3 / 0.6, abs=0.03)
    np.testing.assert_allclose(s["object_colour_ratio"], [1.2, 1.0, 1.0], atol=0.02)
    assert np.isfinite(s["psnr_region"])
    same = cr.summarise([cr.frame_scores(gt, gt, empty, obj)])
    assert same["psnr_region"] > 100 and same["shadow_depth"] == pytest.approx(1.0)
    assert same["shadow_depth_area"] == pytest.approx(1.0)
    # no shadow, no object: nothing to report rather than a NaN
    none = cr.summarise([cr.frame_scores(srgb_encode(empty), srgb_encode(empty), empty,
                                         np.zeros(obj.shape, bool))])
    assert none == {"psnr_region": None}


def test_area_depth_is_not_charged_with_the_scenes_blurred_texture():
    """A textured empty scene; ours is the same scene blurred (a reconstruction) darkened by
    exactly the truth's shadow: the per-pixel mean ratio reads the blur as a lighter
    shadow, the area ratio does not."""
    from scipy.ndimage import uniform_filter
    empty, _, obj, shadow = _frame()
    rng = np.random.default_rng(0)
    tex = np.repeat(rng.uniform(0.05, 0.6, (48, 64, 1)), 3, -1)
    blurred = uniform_filter(tex, size=(5, 5, 1))
    gt, ours = tex.copy(), blurred.copy()
    gt[shadow] *= 0.4
    ours[shadow] *= 0.4
    gt[obj] = ours[obj] = (0.5, 0.25, 0.1)
    s = cr.summarise([cr.frame_scores(srgb_encode(ours), srgb_encode(gt), tex, obj)])
    assert s["shadow_depth"] < 0.9                           # charged with the blur
    assert s["shadow_depth_area"] == pytest.approx(1.0, abs=0.05)
    assert s["shadow_ratio_truth_area"] == pytest.approx(0.4, abs=0.01)


def test_figures_show_the_shadow_line_and_crops():
    empty, gt, obj, shadow = _frame()
    ys, xs = cr.shadow_line(shadow)
    assert np.ptp(xs) > np.ptp(ys)                   # along the band's long axis
    assert shadow[ys, xs].mean() > 0.4 and not shadow[ys, xs].all()   # in and beyond it
    img = cr.crops_figure(gt, {"ours": gt}, obj, shadow)
    assert img.width > 100 and img.height > 100
    png = cr.profile_png(gt, empty, {"ours": gt}, shadow)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert cr.profile_png(gt, empty, {}, np.zeros_like(shadow)) is None
    with pytest.raises(ValueError, match="neither"):
        cr.crops_figure(gt, {}, np.zeros_like(obj), np.zeros_like(shadow))
