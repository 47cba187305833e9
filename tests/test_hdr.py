"""HDR expansion (exposure model, EV-bracket fusion), light extraction, baseline completions."""
import numpy as np
import pytest
import torch

from comgs_dr.core.colorspace import LUMA
from comgs_dr.lighting import hdr as H

EVS = (0.0, -2.5, -5.0)


def _dirs(h, w):
    return H.equirect_directions(h, w)


def _sky(h=32, w=64):
    """Smooth sky spanning ~1e-3 (nadir) .. ~2 (zenith), slightly coloured."""
    z = _dirs(h, w)[..., 2]
    base = 10.0 ** (-3.0 + 1.65 * (z + 1.0))
    return base[..., None] * np.array([0.9, 1.0, 1.15])


def _add_blob(img, direction, peak, sigma_deg):
    d = _dirs(*img.shape[:2])
    ang = np.degrees(np.arccos(np.clip(d @ np.asarray(direction, float), -1, 1)))
    return img + peak * np.exp(-0.5 * (ang / sigma_deg) ** 2)[..., None]


def _unit_from_angles(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def _bracket(hdr, evs=EVS, scale=None):
    scale = scale or {}
    return {ev: H.expose(hdr * scale.get(ev, 1.0), ev) for ev in evs}


# ---------------------------------------------------------------------------------------
# Exposure model and fusion

@pytest.mark.parametrize("ev", EVS)
def test_expose_unexpose_round_trip(ev):
    white = 2.0 ** -ev
    x = np.geomspace(1e-5, 0.99, 400) * white
    ldr = H.expose(x, ev)
    assert ldr.min() >= 0 and ldr.max() < 1
    np.testing.assert_allclose(H.unexpose(ldr, ev), x, rtol=1e-10)
    assert np.all(H.expose(np.array([1.01, 5.0]) * white, ev) == 1.0)   # saturates
    assert H.expose(np.array([-1.0]), ev)[0] == 0.0


def test_fusion_round_trip_recoverable_range():
    hdr = _add_blob(_sky(), _unit_from_angles(50, 30), 15.0, 4.0)
    hdr[3, 5] = 20.0
    assert hdr.min() < 1.1e-3 and hdr.max() >= 15.0
    fused = H.fuse_brackets(_bracket(hdr))
    np.testing.assert_allclose(fused, hdr, rtol=1e-9)


def test_fusion_saturation_limit():
    hdr = _add_blob(_sky(), _unit_from_angles(50, 30), 1e3, 4.0)
    fused = H.fuse_brackets(_bracket(hdr))
    limit = H.saturation_limit(EVS)
    assert limit == 2.0 ** 5
    assert fused.max() <= limit * (1 + 1e-12)
    over = hdr > limit
    assert over.sum() > 10
    np.testing.assert_allclose(fused[over], limit, rtol=1e-9)    # clipped, not recovered
    np.testing.assert_allclose(fused[~over], hdr[~over], rtol=1e-9)


def test_fusion_8bit_quantised():
    hdr = _add_blob(np.maximum(_sky(), 0.05), _unit_from_angles(40, -60), 15.0, 5.0)
    ldrs = {ev: np.round(v * 255) / 255 for ev, v in _bracket(hdr).items()}
    rel = np.abs(H.fuse_brackets(ldrs) / hdr - 1)
    assert rel.max() < 0.03


def test_fusion_blend_is_continuous_for_inconsistent_brackets():
    # A generator's EV -2.5 output 20 % too bright: a hard switch would jump by 20 %.
    x = np.geomspace(1e-3, 31.0, 4000)
    hdr = np.repeat(x[None, :, None], 3, -1)
    fused = H.fuse_brackets(_bracket(hdr, scale={-2.5: 1.2}))[0, :, 0]
    step = np.abs(np.diff(np.log(fused)))
    assert step.max() < 0.01           # a hard switch would step by log(1.2) ≈ 0.18


def test_fusion_keys_and_shapes():
    hdr = _sky(4, 8)
    ldrs = {int(0): H.expose(hdr, 0), -2.5: H.expose(hdr, -2.5), -5: H.expose(hdr, -5)}
    np.testing.assert_allclose(H.fuse_brackets(ldrs), hdr, rtol=1e-9)   # int/float keys
    with pytest.raises(ValueError, match="no LDR panorama for EV -5"):
        H.fuse_brackets({0.0: ldrs[0], -2.5: ldrs[-2.5]})
    with pytest.raises(ValueError, match="shapes differ"):
        H.fuse_brackets({**ldrs, -5: ldrs[-5][:2]})
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        H.fuse_brackets({e: v[..., :2] for e, v in ldrs.items()})


def test_torch_gradcheck_fusion_and_expose():
    g = torch.Generator().manual_seed(0)
    ldrs = {}
    for ev in EVS:
        x = 0.06 + 0.74 * torch.rand(2, 3, 3, generator=g, dtype=torch.float64)
        x[0, 0] = torch.tensor([0.90, 0.50, 0.30])     # inside the blend ramp
        x[0, 1] = torch.tensor([0.20, 0.88, 0.40])     # inside the blend ramp
        x[1, 0] = torch.tensor([0.97, 0.60, 0.20])     # past sat: darker exposure wins
        ldrs[ev] = x.requires_grad_()
    keys = list(ldrs)

    def f(*xs):
        return H.fuse_brackets(dict(zip(keys, xs)))
    assert torch.autograd.gradcheck(f, tuple(ldrs[k] for k in keys))
    assert torch.autograd.gradcheck(
        lambda *xs: H.fuse_brackets(dict(zip(keys, xs)), measure="luma"),
        tuple(ldrs[k] for k in keys))
    hdr = (0.02 + 0.7 * torch.rand(2, 3, 3, generator=g, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: H.expose(x, -1.0), (hdr,))
    ldr = (0.06 + 0.9 * torch.rand(2, 3, 3, generator=g, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: H.unexpose(x, -2.5), (ldr,))


def test_torch_gradients_finite_at_kinks():
    x = torch.tensor([0.0, 0.0031308, 1e-9, 1.0, 2.0], dtype=torch.float64, requires_grad=True)
    H.expose(x, 0).sum().backward()
    assert torch.isfinite(x.grad).all()
    y = torch.tensor([0.0, 0.04045, 1.0, 1.5], dtype=torch.float64, requires_grad=True)
    H.unexpose(y, -5).sum().backward()
    assert torch.isfinite(y.grad).all()


def test_numpy_torch_agree():
    hdr = _add_blob(_sky(8, 16), _unit_from_angles(60, 10), 15.0, 20.0)
    for ev in EVS:
        a = H.expose(hdr, ev)
        b = H.expose(torch.from_numpy(hdr), ev)
        assert isinstance(b, torch.Tensor)
        np.testing.assert_allclose(b.numpy(), a, rtol=0, atol=1e-14)
        np.testing.assert_allclose(H.unexpose(torch.from_numpy(a), ev).numpy(),
                                   H.unexpose(a, ev), rtol=1e-13)
    ldrs = {ev: np.round(v * 255) / 255 for ev, v in _bracket(hdr * 1.3).items()}
    for measure in ("max", "luma"):
        a = H.fuse_brackets(ldrs, measure=measure)
        b = H.fuse_brackets({e: torch.from_numpy(v) for e, v in ldrs.items()}, measure=measure)
        np.testing.assert_allclose(b.numpy(), a, rtol=1e-12)
    assert H.expose(hdr.astype(np.float32), 0).dtype == np.float32


# ---------------------------------------------------------------------------------------
# Lights

def _disk_sun(img, direction, radiance, radius_deg, sub=6):
    """Add an anti-aliased disk (sub×sub supersampled coverage); returns analytic power."""
    h, w = img.shape[:2]
    o = (np.arange(sub) + 0.5) / sub
    u = ((np.arange(w)[:, None] + o[None]) / w).ravel()
    v = ((np.arange(h)[:, None] + o[None]) / h).ravel()
    uu, vv = np.meshgrid(u, v)
    from comgs_dr.core.equirect import equirect_uv_to_dir_np
    d = equirect_uv_to_dir_np(np.stack([uu.ravel(), vv.ravel()], -1))
    inside = d @ direction >= np.cos(np.radians(radius_deg))
    # supersample weights ∝ sin θ within a pixel so coverage is a solid-angle fraction
    wt = np.sqrt(np.maximum(1 - d[:, 2] ** 2, 0))
    cov = (inside * wt).reshape(h, sub, w, sub).sum((1, 3)) / \
        wt.reshape(h, sub, w, sub).sum((1, 3))
    img = img + radiance * cov[..., None] * np.array([1.0, 0.9, 0.8])
    return img, radiance * np.array([1.0, 0.9, 0.8]) * 2 * np.pi * (1 - np.cos(np.radians(radius_deg)))


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.dot(a, b), -1, 1)))


@pytest.mark.parametrize("theta,phi", [(55, 40), (70, 180), (35, -179.5), (1.0, 0.0)],
                         ids=["plain", "seam", "seam-off-centre", "pole"])
def test_extract_lights_planted_sun(theta, phi):
    d0 = _unit_from_angles(theta, phi)
    img, power = _disk_sun(_sky(128, 256), d0, 800.0, 3.0)
    lights = H.extract_lights(img, k=3)
    top = lights[0]
    assert _angle_deg(top["direction"], d0) < 2.0
    np.testing.assert_allclose(top["rgb_power"], power, rtol=0.10)
    assert abs(np.linalg.norm(top["direction"]) - 1) < 1e-12
    np.testing.assert_allclose(top["mean_radiance"], top["rgb_power"] / top["solid_angle"])
    assert top["peak_luminance"] == pytest.approx(float((img @ LUMA).max()))   # the sun's
    assert top["solid_angle"] < 0.05
    if phi == 180:   # really straddles the seam: both edge columns lit
        assert img[:, 0, 0].max() > 100 and img[:, -1, 0].max() > 100


def test_extract_lights_ranking_and_black():
    img, p1 = _disk_sun(_sky(64, 128), _unit_from_angles(60, 100), 2000.0, 5.0)
    img, p2 = _disk_sun(img, _unit_from_angles(80, -30), 400.0, 5.0)
    lights = H.extract_lights(img, k=2, threshold_quantile=0.99)
    assert len(lights) == 2
    assert _angle_deg(lights[0]["direction"], _unit_from_angles(60, 100)) < 2
    assert _angle_deg(lights[1]["direction"], _unit_from_angles(80, -30)) < 2
    np.testing.assert_allclose(lights[1]["rgb_power"], p2, rtol=0.1)
    assert H.extract_lights(np.zeros((8, 16, 3))) == []
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        H.extract_lights(np.ones((8, 16)))


def test_label_equirect_seam_and_pole():
    m = np.zeros((8, 16), bool)
    m[3:5, 0] = m[4:6, 15] = True          # seam (diagonal contact included)
    m[0, 2] = m[0, 10] = True              # antipodal across the north pole
    m[6, 7] = True                         # isolated
    lab, n = H.label_equirect(m)
    assert n == 3
    assert lab[3, 0] == lab[5, 15] and lab[0, 2] == lab[0, 10] != lab[3, 0]
    assert H.pixel_solid_angles(8, 16).sum() * 16 == pytest.approx(4 * np.pi)


# ---------------------------------------------------------------------------------------
# Baseline completions

FILLS = [H.mean_fill, H.push_pull_fill, H.sh_fill]


def _partial(h=32, w=64, seed=0):
    rng = np.random.default_rng(seed)
    img = _add_blob(_sky(h, w), _unit_from_angles(60, 20), 5.0, 15.0)
    mask = np.ones((h, w))
    mask[: h // 3] = 0                                 # upper hemisphere missing
    mask[rng.random((h, w)) < 0.15] = 0                # needle-like dropouts
    return img, mask


@pytest.mark.parametrize("fill", FILLS, ids=lambda f: f.__name__)
def test_fill_keeps_observed_and_is_finite(fill):
    img, mask = _partial()
    holes = mask == 0
    inp = img.copy()
    inp[holes] = np.nan                                # hole content is ignored
    out = fill(inp, mask)
    assert out.shape == img.shape and out.dtype == img.dtype
    assert np.array_equal(out[~holes], img[~holes])
    assert np.isfinite(out).all() and out[holes].min() >= 0
    assert fill(img.astype(np.float32), mask).dtype == np.float32
    full = fill(img, np.ones(mask.shape))
    assert np.array_equal(full, img)


def test_mean_fill_is_solid_angle_weighted():
    img = np.zeros((16, 32, 1))
    img[:8] = 1.0                                      # north hemisphere 1, south 0
    mask = np.ones((16, 32))
    mask[:, :16] = 0
    mask[0, 20] = 0                                    # leave a hole near the pole too
    out = H.mean_fill(img, mask)
    dw = np.broadcast_to(H.pixel_solid_angles(16, 32), (16, 32))
    m = mask > 0
    assert out[0, 0, 0] == pytest.approx((img[..., 0] * dw)[m].sum() / dw[m].sum())


def test_push_pull_seam():
    h, w = 32, 64
    img, mask = _partial(h, w, seed=3)
    # seam-symmetric input (column x ≡ column W-1-x) with a hole straddling the seam
    sym = 0.5 * (img + img[:, ::-1])
    msk = np.ones((h, w))
    msk[10:22, :6] = msk[10:22, -6:] = 0
    out = H.push_pull_fill(sym, msk)
    np.testing.assert_allclose(out[:, 0], out[:, -1], rtol=1e-12)
    # circular: filling a rolled panorama == rolling the fill (u is periodic)
    a = H.push_pull_fill(img, mask)
    b = H.push_pull_fill(np.roll(img, w // 2, 1), np.roll(mask, w // 2, 1))
    np.testing.assert_allclose(np.roll(b, -(w // 2), 1), a, rtol=1e-12)
    # hole across the seam: the fill is as continuous across u=0/1 as inside the image
    msk = np.ones((h, w))
    msk[4:28, -10:] = msk[4:28, :10] = 0
    out = H.push_pull_fill(img, msk)
    seam_jump = np.abs(out[4:28, 0] - out[4:28, -1]).max()
    inner_jump = np.abs(np.diff(out[4:28, 1:-1], axis=1)).max()
    assert seam_jump <= 1.5 * inner_jump


@pytest.mark.parametrize("cover", ["random", "lower"])
@pytest.mark.parametrize("order", [1, 2])
def test_sh_fill_reproduces_order1(cover, order):
    h, w = 32, 64
    d = _dirs(h, w)
    coef = np.array([[1.0, 0.3, -0.2, 0.4], [0.8, -0.1, 0.25, 0.3], [1.2, 0.2, 0.2, -0.3]])
    f = coef[:, 0] + d @ coef[:, 1:].T                # a + b·d: exactly order 1, > 0
    assert f.min() > 0
    if cover == "random":
        mask = (np.random.default_rng(1).random((h, w)) < 0.5).astype(float)
    else:
        mask = (d[..., 2] < 0).astype(float)
    assert 0.45 < mask.mean() < 0.55
    out = H.sh_fill(f, mask, order=order)
    assert np.abs(out - f).max() < 1e-3


def test_sh_fill_clamps_and_basis_orthonormal():
    d = _dirs(32, 64)
    f = (d[..., 2:3] - 0.2) * np.ones(3)               # negative in the south
    mask = (d[..., 2] > 0.3).astype(float)
    out = H.sh_fill(f, mask, order=1)
    assert out.min() >= 0 and np.array_equal(out[mask > 0], f[mask > 0])
    hh, ww = 96, 192
    y = H.real_sh_basis(_dirs(hh, ww).reshape(-1, 3), 3)
    dw = np.broadcast_to(H.pixel_solid_angles(hh, ww), (hh, ww)).ravel()
    np.testing.assert_allclose(y.T @ (y * dw[:, None]), np.eye(16), atol=2e-3)


@pytest.mark.parametrize("fill", FILLS, ids=lambda f: f.__name__)
def test_fill_bad_inputs(fill):
    img, mask = _partial(8, 16)
    with pytest.raises(ValueError, match="zero coverage"):
        fill(img, np.zeros_like(mask))
    with pytest.raises(ValueError, match=r"rgb must be \[H, W, C\]"):
        fill(img[..., 0], mask)
    with pytest.raises(ValueError, match="mask must be"):
        fill(img, mask[:, :8])
    with pytest.raises(ValueError, match=r"mask values"):
        fill(img, mask * 2)
    for bad in (np.nan, np.inf):
        x = img.copy()
        x[np.argwhere(mask > 0)[0][0], np.argwhere(mask > 0)[0][1], 1] = bad
        with pytest.raises(ValueError, match="NaN/Inf"):
            fill(x, mask)
    if fill is H.sh_fill:
        with pytest.raises(ValueError, match="order"):
            fill(img, mask, order=-1)


def test_clipped_sky_fraction_is_the_clipped_share_of_the_seen_sky():
    """Clipped above 30° elevation (half the upper hemisphere's solid angle) -> ½; unobserved
    or below-horizon clipping does not count; no sky seen -> 0."""
    h, w = 90, 180
    el = np.degrees(np.arcsin(H.equirect_directions(h, w)[..., 2]))                   # [h, w]
    ldr = np.full((h, w, 3), 0.4)
    ldr[el > 30.0] = 1.0
    mask = np.ones((h, w))
    assert H.clipped_sky_fraction(ldr, mask) == pytest.approx(0.5, abs=0.02)
    ldr[el < -30.0] = 1.0                                     # a blown-out floor: not sky
    assert H.clipped_sky_fraction(ldr, mask) == pytest.approx(0.5, abs=0.02)
    mask[el > 30.0] = 0.0                                     # the clipped part unobserved
    assert H.clipped_sky_fraction(ldr, mask) == 0.0
    mask[el > 0.0] = 0.0
    assert H.clipped_sky_fraction(ldr, mask) == 0.0           # no sky seen
    ldr[..., 0] = 0.2                                          # one channel below: still clipped
    mask[:] = 1.0
    assert H.clipped_sky_fraction(ldr, mask) == pytest.approx(0.5, abs=0.02)


def test_seen_sky_fraction_counts_the_observed_upper_hemisphere():
    h, w = 90, 180
    el = np.degrees(np.arcsin(H.equirect_directions(h, w)[..., 2]))
    mask = (el < 0).astype(float)                                   # ground only
    assert H.seen_sky_fraction(mask) == 0.0
    mask[el > 30.0] = 1.0                                           # half the sky's solid angle
    assert H.seen_sky_fraction(mask) == pytest.approx(0.5, abs=0.02)
    assert H.seen_sky_fraction(np.ones((h, w, 1))) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="finite"):
        H.seen_sky_fraction(np.full((h, w), np.nan))
    with pytest.raises(ValueError, match=r"\[H, W, 1\]"):
        H.seen_sky_fraction(np.ones((h, w, 3)))                   # an image, not a mask
