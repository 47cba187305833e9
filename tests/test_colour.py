"""core.colorspace against colour-science: NumPy paths are colour-science; the hand-written
Dr.Jit and torch sRGB transfers match its values (0, the knee, 1, HDR up to 1e6)."""
import subprocess
import sys

import colour
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core import colorspace as cs
from comgs_dr.core.hostarray import to_jit

RTOL = 1e-6   # measured max: 6.8e-7 encode (at the 0.0031308 knee, where the two IEC
#               branches differ), 7.8e-7 Dr.Jit / 7.7e-7 torch float32 decode


def _values(seed=0, n=40_000):
    """float32 test values: 0, both knees (and a float32 step either side), 1, 1e6, log-uniform
    1e-8..1e6 and uniform [0, 1]."""
    rng = np.random.default_rng(seed)
    knees = np.array([0.0031308, 0.04045, 12.92 * 0.0031308], np.float32)
    special = np.concatenate([[0.0, 1.0, 1e6, 1e-8], knees, np.nextafter(knees, 0),
                              np.nextafter(knees, 1)])
    x = np.concatenate([special, 10 ** rng.uniform(-8, 6, n), rng.uniform(0, 1, n)])
    return x.astype(np.float32)


def _close(out, ref):
    out, ref = np.asarray(out, np.float64), np.asarray(ref, np.float64)
    assert np.all(np.isfinite(out))
    rel = np.abs(out - ref) / np.maximum(np.abs(ref), 1e-30)
    assert rel.max() <= RTOL, (rel.max(), out[rel.argmax()], ref[rel.argmax()])


def test_numpy_paths_are_colour_science_with_the_old_semantics():
    x = np.array([-0.5, -1e-3, 0.0, 0.0031308, 0.5, 1.0, 2.0, 1e6])
    np.testing.assert_array_equal(cs.srgb_encode(x), colour.cctf_encoding(x, function="sRGB"))
    np.testing.assert_array_equal(cs.srgb_decode(x), colour.cctf_decoding(x, function="sRGB"))
    # the package's semantics (unchanged): the linear segment extends to negatives, values
    # above 1 follow the power curve, no clamp (callers clip), float32 stays float32
    old_enc = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.abs(x) ** (1 / 2.4) - 0.055)
    old_dec = np.where(x <= 0.04045, x / 12.92, ((np.abs(x) + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(cs.srgb_encode(x), old_enc, rtol=1e-12)
    np.testing.assert_allclose(cs.srgb_decode(x), old_dec, rtol=1e-6)   # knee: 0.0404500 vs 12.92·0.0031308
    assert cs.srgb_encode(-0.1) == pytest.approx(-1.292) and cs.srgb_encode(2.0) > 1.0
    assert cs.srgb_encode(np.float32([0.5])).dtype == np.float32
    y = _values(1)
    # round trip: exact but at the knee, where IEC's two thresholds leave a 7e-7 step
    np.testing.assert_allclose(cs.srgb_decode(cs.srgb_encode(y.astype(np.float64))), y, rtol=1e-6)


def test_drjit_transfers_match_colour_science():
    x = _values()
    xd = x.astype(np.float64)
    _close(cs.linear_to_srgb(to_jit(mi.Float, x)), colour.cctf_encoding(xd, function="sRGB"))
    _close(cs.srgb_to_linear(to_jit(mi.Float, x)), colour.cctf_decoding(xd, function="sRGB"))
    # documented difference: negatives -> 0 (colour-science extends the linear segment)
    neg = mi.Float([-1.0, -1e-3])
    assert np.all(np.asarray(cs.linear_to_srgb(neg)) == 0) and np.all(np.asarray(cs.srgb_to_linear(neg)) == 0)


def test_drjit_transfers_differentiable():
    x = mi.Float([0.0, 0.002, 0.0031308, 0.2, 1.0, 50.0])
    dr.enable_grad(x)
    y = cs.linear_to_srgb(x) + cs.srgb_to_linear(x)
    dr.backward(dr.sum(y))
    g = np.asarray(dr.grad(x))
    xd = np.asarray(x, np.float64)
    h = 1e-6 * np.maximum(xd, 1e-3)
    f = lambda v: colour.cctf_encoding(v, function="sRGB") + colour.cctf_decoding(v, function="sRGB")  # noqa: E731
    fd = (f(xd + h) - f(np.maximum(xd - h, 0))) / (xd + h - np.maximum(xd - h, 0))
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g[[1, 3, 4, 5]], fd[[1, 3, 4, 5]], rtol=2e-3)


def test_torch_transfers_match_colour_science():
    torch = pytest.importorskip("torch")
    x = _values(2)
    for dt in (torch.float32, torch.float64):
        t = torch.tensor(x, dtype=dt, requires_grad=True)
        xd = t.detach().double().numpy()
        enc, dec = cs.srgb_encode(t), cs.srgb_decode(t)
        assert enc.dtype == dt
        _close(enc.detach().double().numpy(), colour.cctf_encoding(xd, function="sRGB"))
        _close(dec.detach().double().numpy(), colour.cctf_decoding(xd, function="sRGB"))
        (enc.sum() + dec.sum()).backward()
        assert torch.isfinite(t.grad).all()
    t = torch.tensor([-0.5, -1e-3], dtype=torch.float64)          # negatives: linear, as NumPy
    np.testing.assert_allclose(cs.srgb_encode(t).numpy(), cs.srgb_encode(t.numpy()), rtol=1e-12)
    np.testing.assert_allclose(cs.srgb_decode(t).numpy(), cs.srgb_decode(t.numpy()), rtol=1e-12)


def test_luma_and_luminance_are_the_srgb_colourspace():
    m = colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ
    np.testing.assert_array_equal(cs.LUMA, m[1])
    rgb = np.random.default_rng(3).random((7, 5, 3)) * 100
    np.testing.assert_allclose(cs.luminance(rgb), rgb @ cs.LUMA, rtol=1e-12)
    cs_ = colour.RGB_COLOURSPACES["sRGB"]
    np.testing.assert_allclose(cs.luminance(rgb), colour.RGB_luminance(rgb, cs_.primaries, cs_.whitepoint),
                               rtol=4e-4)   # primaries-derived Y row vs IEC's rounded one:
    # 0.2126729 / 0.7151522 / 0.0721750 vs 0.2126 / 0.7152 / 0.0722, at most 3.5e-4 apart


def test_tonemap_reinhard_on_luminance():
    rng = np.random.default_rng(4)
    hdr = np.concatenate([10 ** rng.uniform(-4, 4, (200, 1)) * rng.random((200, 3)),
                          [[0, 0, 0], [1e6, 1e6, 1e6], [5.0, 0.0, 0.0]]])
    out = cs.tonemap(hdr)
    assert out.shape == hdr.shape and out.min() >= 0 and out.max() <= 1
    assert np.all(out[-3] == 0) and np.allclose(out[-2], 1, atol=1e-6)
    lin = cs.srgb_decode(out)
    lum = hdr @ cs.LUMA
    ok = out.max(-1) < 1                                    # not clipped
    assert ok.sum() > 100
    np.testing.assert_allclose(lin[ok] @ cs.LUMA, (lum / (1 + lum))[ok], rtol=1e-9)   # L/(1+L)
    ratio = lin[ok] / np.maximum(hdr[ok], 1e-300)                                     # hue kept
    big = hdr[ok] > 1e-3 * hdr[ok].max(-1, keepdims=True)
    assert np.allclose(np.where(big, ratio, ratio.max(-1, keepdims=True)), ratio.max(-1, keepdims=True), rtol=1e-9)
    assert np.all(np.diff(cs.tonemap(np.linspace(0, 100, 50)[:, None] * [[0.3, 0.5, 0.2]]) @ cs.LUMA) > 0)


def test_package_import_does_not_import_colour():
    code = ("import sys, comgs_dr, comgs_dr.core.colorspace, comgs_dr.core.exr, comgs_dr.cli; "
            "print('colour' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
