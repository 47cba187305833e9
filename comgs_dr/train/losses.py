"""Reconstruction losses of ComGS step 1 (2D Gaussian surfels), differentiable in Dr.Jit.

Paper (reconstruction, step 1)::

    L_rgb  = L1(C, C_gt) + λ_ssim · (1 − SSIM(C, C_gt))              (λ_ssim = 0.2)
    L_d2n  = 1 − N · N_d          N_d: normal of the unbiased-depth surface
    L_mask = −K log W − (1 − K) log(1 − W)   K: object mask, W: rendered weight
    L      = L_rgb + λ_d2n L_d2n + λ_mask L_mask                    (λ_d2n = λ_mask = 0.05)

Note: 3DGS/2DGS write the photometric term as (1 − λ)·L1 + λ·D-SSIM with λ = 0.2,
i.e. 0.8·L1 + 0.2·(1 − SSIM); ComGS's form keeps the full L1 weight (``rgb_loss``).

Images are ``mi.TensorXf`` [H, W, C] (``mi.render`` output / ``SurfelGBuffer.split``);
[H, W] is accepted for one-channel buffers and numpy arrays are converted (constants).
Every kernel works on the flat row-major arrays (index = (y·W + x)·C + c) with
vectorised masked gathers — no Python loop over pixels. Scalar losses are
``mi.Float`` of width 1, ready for ``dr.backward``. Written against ``mi.*`` types
so it runs in ``llvm_ad_rgb`` and ``cuda_ad_rgb`` alike.
"""
from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit

__all__ = ["l1", "gaussian_window", "blur", "ssim_map", "ssim", "rgb_loss",
           "depth_to_normal", "d2n_loss", "mask_loss", "Step1Loss"]


# ------------------------------------------------------------------ helpers
def _tensor(x, name: str) -> mi.TensorXf:
    """``x`` as an mi.TensorXf (mi tensors pass through untouched, keeping their AD graph)."""
    if isinstance(x, mi.TensorXf):
        return x
    if isinstance(x, dr.ArrayBase) and not dr.is_tensor_v(x):
        raise ValueError(f"{name}: expected an mi.TensorXf [H, W, C], got {type(x).__name__}")
    a = np.asarray(x, dtype=np.float32)
    if a.ndim == 0:
        raise ValueError(f"{name}: expected an image [H, W, C], got a scalar")
    return to_jit(mi.TensorXf, a)


def _image(x, name: str, channels: int | None = None):
    """(flat mi.Float, H, W, C) of an image [H, W, C] or [H, W] (C = 1)."""
    t = _tensor(x, name)
    shape = tuple(t.shape)
    if len(shape) == 2:
        shape = (shape[0], shape[1], 1)
    if len(shape) != 3:
        raise ValueError(f"{name}: expected shape [H, W, C] or [H, W], got {list(t.shape)}")
    H, W, C = shape
    if H < 1 or W < 1 or C < 1:
        raise ValueError(f"{name}: empty image of shape {list(t.shape)}")
    if channels is not None and C != channels:
        raise ValueError(f"{name}: expected {channels} channel(s), got shape {list(t.shape)}")
    return t.array, H, W, C


def _same_shape(sa, sb, na: str, nb: str):
    if sa != sb:
        raise ValueError(f"{na} and {nb} must have the same shape [H, W, C], got "
                         f"{list(sa)} and {list(sb)}")


def _vec3(flat: mi.Float) -> mi.Vector3f:
    """Per-pixel Vector3f [H·W] from a flat [H·W·3] array (differentiable gathers)."""
    return dr.unravel(mi.Vector3f, flat)


def _flat3(v: mi.Vector3f) -> mi.Float:
    """Flat [H·W·3] (pixel-major) array from a per-pixel Vector3f."""
    return dr.ravel(v)


def _scalar(x) -> float:
    return float(x[0]) if dr.width(x) >= 1 else float("nan")


# ------------------------------------------------------------------ L1
def l1(a, b, mask=None) -> mi.Float:
    """L1 = mean |a − b| over pixels and channels; with ``mask`` [H, W(, 1)] (weights in
    [0, 1]) the mean is Σ m |a − b| / (C · Σ m) over the masked pixels (0 if Σ m = 0)."""
    fa, H, W, C = _image(a, "l1: a")
    fb, *sb = _image(b, "l1: b")
    _same_shape((H, W, C), tuple(sb), "l1: a", "l1: b")
    d = dr.abs(fa - fb)                                                    # [H·W·C]
    if mask is None:
        return dr.mean(d)
    fm, Hm, Wm, Cm = _image(mask, "l1: mask", channels=1)
    _same_shape((H, W), (Hm, Wm), "l1: a [H, W]", "l1: mask [H, W]")
    m = dr.detach(dr.repeat(fm, C)) if C > 1 else dr.detach(fm)           # [H·W·C]
    return dr.sum(m * d) / dr.maximum(dr.sum(m), 1e-12)


# ------------------------------------------------------------------ SSIM
def gaussian_window(window: int = 11, sigma: float = 1.5) -> list[float]:
    """Normalised 1-D Gaussian taps g[k] ∝ exp(−(k − window//2)² / 2σ²) (3DGS ``gaussian``)."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"gaussian_window: window must be odd and ≥ 1, got {window}")
    if not sigma > 0:
        raise ValueError(f"gaussian_window: sigma must be > 0, got {sigma}")
    r = window // 2
    g = [math.exp(-((k - r) ** 2) / (2.0 * sigma * sigma)) for k in range(window)]
    s = sum(g)
    return [v / s for v in g]


def _blur_raw(a: mi.Float, H: int, W: int, C: int, taps) -> mi.Float:
    """Separable zero-padded correlation with symmetric ``taps`` (rows, then columns)."""
    r = len(taps) // 2
    idx = mi.Int32(dr.arange(mi.UInt32, H * W * C))
    pix = idx // C
    x, y = pix % W, pix // W
    for coord, size, stride in ((x, W, C), (y, H, W * C)):
        out = dr.zeros(mi.Float, H * W * C)
        for k, g in enumerate(taps):
            o = k - r
            if abs(o) >= size:
                continue                     # tap entirely in the zero padding
            ok = (coord + o >= 0) & (coord + o < size)
            out = dr.fma(dr.gather(mi.Float, a, mi.UInt32(idx + o * stride), ok), g, out)
        a = out
        dr.eval(a)   # the next pass gathers from it
    return a


class _Blur(dr.CustomOp):
    """Gaussian blur B as a custom op: B is symmetric (zero padding, symmetric taps),
    so Bᵀ = B and the adjoint is a blur too — gathers only, no scatter-add."""

    def eval(self, a, H, W, C, taps):
        self.dims = (H, W, C, taps)
        return _blur_raw(a, H, W, C, taps)

    def forward(self):
        self.set_grad_out(_blur_raw(mi.Float(self.grad_in("a")), *self.dims))

    def backward(self):
        self.set_grad_in("a", _blur_raw(mi.Float(self.grad_out()), *self.dims))

    def name(self):
        return "GaussianBlur"


def blur(img, window: int = 11, sigma: float = 1.5) -> mi.TensorXf:
    """Per-channel Gaussian blur [H, W, C] → [H, W, C], as
    ``F.conv2d(img, g gᵀ, padding=window//2, groups=C)`` (two separable passes)."""
    fa, H, W, C = _image(img, "blur: img")
    out = _blur_flat(fa, H, W, C, gaussian_window(window, sigma))
    return mi.TensorXf(out, shape=(H, W, C))


def _blur_flat(a: mi.Float, H, W, C, taps) -> mi.Float:
    if dr.grad_enabled(a):
        return dr.custom(_Blur, a, H, W, C, taps)
    return _blur_raw(a, H, W, C, taps)


def _ssim_flat(a, b, H, W, C, window, sigma, C1, C2) -> mi.Float:
    taps = gaussian_window(window, sigma)
    mu1 = _blur_flat(a, H, W, C, taps)                                     # [H·W·C]
    mu2 = _blur_flat(b, H, W, C, taps)
    mu11, mu22, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s11 = _blur_flat(a * a, H, W, C, taps) - mu11                          # σ_a²
    s22 = _blur_flat(b * b, H, W, C, taps) - mu22                          # σ_b²
    s12 = _blur_flat(a * b, H, W, C, taps) - mu12                          # σ_ab
    return ((2.0 * mu12 + C1) * (2.0 * s12 + C2)) / ((mu11 + mu22 + C1) * (s11 + s22 + C2))


def ssim_map(a, b, window: int = 11, sigma: float = 1.5, C1: float = 0.01 ** 2,
             C2: float = 0.03 ** 2) -> mi.TensorXf:
    """SSIM map [H, W, C] (eq. SSIM, 3DGS/2DGS ``_ssim``): Gaussian-window local
    statistics μ, σ², σ_ab with zero padding window//2,
    SSIM = (2μ_aμ_b + C1)(2σ_ab + C2) / ((μ_a² + μ_b² + C1)(σ_a² + σ_b² + C2))."""
    fa, H, W, C = _image(a, "ssim: a")
    fb, *sb = _image(b, "ssim: b")
    _same_shape((H, W, C), tuple(sb), "ssim: a", "ssim: b")
    return mi.TensorXf(_ssim_flat(fa, fb, H, W, C, window, sigma, C1, C2), shape=(H, W, C))


def ssim(a, b, window: int = 11, sigma: float = 1.5, C1: float = 0.01 ** 2,
         C2: float = 0.03 ** 2) -> mi.Float:
    """Mean SSIM over pixels and channels (3DGS ``ssim(img1, img2)``, size_average)."""
    return dr.mean(ssim_map(a, b, window, sigma, C1, C2).array)


def rgb_loss(c, gt, lambda_ssim: float = 0.2) -> mi.Float:
    """L_rgb = L1(C, C_gt) + λ_ssim (1 − SSIM(C, C_gt)) (ComGS step 1).

    3DGS/2DGS use (1 − λ) L1 + λ (1 − SSIM) = 0.8·L1 + 0.2·D-SSIM instead."""
    fa, H, W, C = _image(c, "rgb_loss: c")
    fb, *sb = _image(gt, "rgb_loss: gt")
    _same_shape((H, W, C), tuple(sb), "rgb_loss: c", "rgb_loss: gt")
    s = dr.mean(_ssim_flat(fa, fb, H, W, C, 11, 1.5, 0.01 ** 2, 0.03 ** 2))
    return dr.mean(dr.abs(fa - fb)) + lambda_ssim * (1.0 - s)






# ------------------------------------------------------------------ depth → normal
def _depth_normal_flat(depth, ray_dirs, origin, weight, min_weight):
    """(N_d Vector3f [H·W], valid Bool [H·W], H, W)."""
    fd, H, W, _ = _image(depth, "depth", channels=1)
    fr, Hr, Wr, _ = _image(ray_dirs, "ray_dirs", channels=3)
    _same_shape((H, W), (Hr, Wr), "depth [H, W]", "ray_dirs [H, W]")
    d = dr.normalize(_vec3(dr.detach(fr)))                                 # [H·W] unit rays
    o = _origins(origin, H, W)
    ok = dr.isfinite(fd) & (fd > 0)                                        # [H·W]
    if weight is not None:
        fw, Hw, Ww, _ = _image(weight, "weight", channels=1)
        _same_shape((H, W), (Hw, Ww), "depth [H, W]", "weight [H, W]")
        ok &= dr.detach(fw) >= min_weight
    D = dr.select(ok, fd, 0.0)            # sanitised: NaN/inf never enter the graph
    X = dr.fma(d, D, o)                                                    # [H·W] points
    dr.eval(X, ok)
    idx = dr.arange(mi.UInt32, H * W)
    x, y = idx % W, idx // W
    interior = (x > 0) & (x + 1 < W) & (y > 0) & (y + 1 < H)
    nb = {}
    for key, off in (("r", 1), ("l", -1), ("d", W), ("u", -W)):
        j = mi.UInt32(mi.Int32(idx) + off)
        nb[key] = (dr.gather(mi.Vector3f, X, j, interior), dr.gather(mi.Bool, ok, j, interior))
    h = nb["r"][0] - nb["l"][0]                                            # ∂X/∂x · 2
    v = nb["d"][0] - nb["u"][0]                                            # ∂X/∂y · 2
    c = dr.cross(h, v)
    l2 = dr.squared_norm(c)
    valid = interior & ok & nb["r"][1] & nb["l"][1] & nb["d"][1] & nb["u"][1]
    valid &= (l2 > 1e-12 * dr.squared_norm(h) * dr.squared_norm(v)) & (l2 > 0)
    n = c * dr.rsqrt(dr.maximum(l2, 1e-30))
    n = dr.select(dr.dot(n, d) > 0, -n, n)                                 # face the camera
    return dr.select(valid, n, 0.0), valid, H, W


def depth_to_normal(depth, ray_dirs, origin, weight=None, min_weight: float = 0.5,
                    return_valid: bool = False):
    """N_d [H, W, 3]: normal of the depth surface (eq. L_d2n, as 2DGS ``depth_to_normal``).

    Back-projects x = o + D̃·d (D̃ [H, W(, 1)] the distance along the unit ray d
    [H, W, 3] from o: per-pixel origins [H, W, 3] from ``camera_rays`` for G-buffer
    depth, or one 3-vector if D̃ is measured from a single point), then
    N_d = normalise((x[y, x+1] − x[y, x−1]) × (x[y+1, x] − x[y−1, x])), flipped so that
    N_d · d < 0. Zero where invalid: image border, a pixel or one of its 4 neighbours
    with depth ≤ 0 / non-finite or (if ``weight`` is given) weight < ``min_weight``, or
    degenerate (parallel) differences. Differentiable w.r.t. the depth.
    With ``return_valid`` also returns the validity mask (mi.Bool [H·W], row-major).
    """
    n, valid, H, W = _depth_normal_flat(depth, ray_dirs, origin, weight, min_weight)
    out = mi.TensorXf(_flat3(n), shape=(H, W, 3))
    return (out, valid) if return_valid else out


def d2n_loss(normal, depth_unbiased, weight, rays, origin, min_weight: float = 0.5,
             detach_depth_normal: bool = False) -> mi.Float:
    """L_d2n = Σ_valid W (1 − N · N_d) / #valid (eq. L_d2n, weighted as 2DGS).

    N [H, W, 3] is the rendered normal as is (Σ T_i α_i n_i, like 2DGS's ``rend_normal``;
    not renormalised), N_d = ``depth_to_normal(D̃)``. Each valid pixel (W ≥
    ``min_weight``, valid depth neighbourhood) is weighted by the detached weight W —
    2DGS multiplies N_d by the detached accumulated opacity — so the loss cannot be
    lowered by making surfels transparent. Gradients reach N and, through N_d, the
    depth (2DGS); ``detach_depth_normal=True`` stops the latter. Returns 0 with no
    valid pixel.
    """
    fn, H, W, _ = _image(normal, "d2n_loss: normal", channels=3)
    fw, Hw, Ww, _ = _image(weight, "d2n_loss: weight", channels=1)
    _same_shape((H, W), (Hw, Ww), "d2n_loss: normal [H, W]", "d2n_loss: weight [H, W]")
    nd, valid, Hd, Wd = _depth_normal_flat(depth_unbiased, rays, origin, weight, min_weight)
    _same_shape((H, W), (Hd, Wd), "d2n_loss: normal [H, W]", "d2n_loss: depth [H, W]")
    if detach_depth_normal:
        nd = dr.detach(nd)
    N = _vec3(fn)                                                          # [H·W]
    e = dr.detach(fw) * (1.0 - dr.dot(N, nd))                              # [H·W]
    count = dr.sum(dr.select(valid, 1.0, 0.0))
    return dr.sum(dr.select(valid, e, 0.0)) / dr.maximum(count, 1.0)


# ------------------------------------------------------------------ mask
def mask_loss(weight, mask, eps: float = 1e-5) -> mi.Float:
    """L_mask = mean(−K log W − (1 − K) log(1 − W)) (binary cross-entropy, eq. L_mask),
    W [H, W(, 1)] clamped to [eps, 1 − eps] (zero gradient where clamped), K the mask."""
    if not 0 < eps < 0.5:
        raise ValueError(f"mask_loss: eps must be in (0, 0.5), got {eps}")
    fw, H, W, _ = _image(weight, "mask_loss: weight", channels=1)
    fk, Hk, Wk, _ = _image(mask, "mask_loss: mask", channels=1)
    _same_shape((H, W), (Hk, Wk), "mask_loss: weight [H, W]", "mask_loss: mask [H, W]")
    w = dr.clip(fw, eps, 1.0 - eps)
    k = dr.detach(fk)
    return dr.mean(-k * dr.log(w) - (1.0 - k) * dr.log(1.0 - w))


def binary_loss(weight, eps: float = 1e-5) -> mi.Float:
    """L_bin = mean(−W log W − (1 − W) log(1 − W)): the entropy of every pixel's coverage,
    lowest when a ray is either fully covered by surfels or not at all. With a learned
    background behind the surfels (``train.background``) it keeps the background from
    showing through half-transparent surfels, where it would learn the near scene (as the
    background entropy losses of radiance-field trainers of unbounded scenes)."""
    fw, *_ = _image(weight, "binary_loss: weight", channels=1)
    w = dr.clip(fw, eps, 1.0 - eps)
    return dr.mean(-w * dr.log(w) - (1.0 - w) * dr.log(1.0 - w))


# ------------------------------------------------------------------ total
@dataclasses.dataclass
class Step1Loss:
    """L = L_rgb + λ_d2n L_d2n + λ_mask L_mask (+ λ_bin L_bin) (ComGS reconstruction step 1).

    ``d2n_from_iteration``: the depth–normal term is off before this iteration (2DGS enables
    its normal loss at 7k of 30k). The defaults are those of ``RadianceConfig`` (object
    preset), which builds this loss with ``RadianceConfig.loss()``.
    """
    lambda_d2n: float = 0.2
    lambda_mask: float = 0.05
    lambda_ssim: float = 0.2
    lambda_binary: float = 0.0
    d2n_from_iteration: int = 300
    d2n_min_weight: float = 0.5
    detach_depth_normal: bool = False
    mask_eps: float = 1e-5

    def d2n_active(self, iteration: int) -> bool:
        return self.lambda_d2n > 0 and iteration >= self.d2n_from_iteration

    def __call__(self, buffers: dict, gt, mask=None, rays=None, iteration: int = 0):
        """Total loss and its parts.

        ``buffers``: ``integrator.split(img)`` (needs ``color``; ``normal``,
        ``depth_unbiased``, ``weight`` for L_d2n; ``weight`` for L_mask); ``gt`` [H, W, 3];
        ``mask`` K [H, W(, 1)] or None (no L_mask); ``rays``: ``camera_rays(sensor)``
        (dirs, origins), needed once L_d2n is on. Returns (total mi.Float [1],
        {"l1", "ssim", "rgb", "d2n", "mask", "total"}: Python floats, for logging).
        """
        if "color" not in buffers:
            raise ValueError("Step1Loss: buffers has no 'color' (render with the colour target)")
        fc, H, W, C = _image(buffers["color"], "Step1Loss: color")
        fg, *sg = _image(gt, "Step1Loss: gt")
        _same_shape((H, W, C), tuple(sg), "Step1Loss: color", "Step1Loss: gt")
        l1v = dr.mean(dr.abs(fc - fg))
        ssimv = dr.mean(_ssim_flat(fc, fg, H, W, C, 11, 1.5, 0.01 ** 2, 0.03 ** 2))
        rgb = l1v + self.lambda_ssim * (1.0 - ssimv)
        total, zero = rgb, mi.Float(0.0)
        d2n = mk = bn = zero
        if self.d2n_active(iteration):
            missing = [k for k in ("normal", "depth_unbiased", "weight") if k not in buffers]
            if missing:
                raise ValueError(f"Step1Loss: L_d2n (iteration {iteration} ≥ "
                                 f"{self.d2n_from_iteration}) needs the buffers {missing}")
            if rays is None:
                raise ValueError("Step1Loss: L_d2n needs rays=camera_rays(sensor)")
            dirs, origins = rays
            d2n = d2n_loss(buffers["normal"], buffers["depth_unbiased"], buffers["weight"],
                           dirs, origins, self.d2n_min_weight, self.detach_depth_normal)
            total = total + self.lambda_d2n * d2n
        if mask is not None and self.lambda_mask > 0:
            if "weight" not in buffers:
                raise ValueError("Step1Loss: L_mask needs the 'weight' buffer")
            mk = mask_loss(buffers["weight"], mask, self.mask_eps)
            total = total + self.lambda_mask * mk
        if self.lambda_binary > 0:
            if "weight" not in buffers:
                raise ValueError("Step1Loss: L_bin needs the 'weight' buffer")
            bn = binary_loss(buffers["weight"], self.mask_eps)
            total = total + self.lambda_binary * bn
        dr.eval(total, l1v, ssimv, rgb, d2n, mk, bn)
        parts = {"l1": _scalar(l1v), "ssim": _scalar(ssimv), "rgb": _scalar(rgb),
                 "d2n": _scalar(d2n), "mask": _scalar(mk), "total": _scalar(total)}
        if self.lambda_binary > 0:
            parts["binary"] = _scalar(bn)
        return total, parts


def _origins(origin, H: int, W: int) -> mi.Vector3f:
    """Per-pixel origins [H·W] from an [H, W, 3] tensor or a single 3-vector (no AD)."""
    if isinstance(origin, mi.TensorXf) or (hasattr(origin, "ndim") and np.ndim(origin) == 3):
        fo, Ho, Wo, Co = _image(origin, "origin", channels=3)
        _same_shape((H, W), (Ho, Wo), "depth [H, W]", "origin [H, W]")
        return _vec3(dr.detach(fo))
    o = np.asarray(origin, dtype=np.float64).reshape(-1)
    if o.shape != (3,):
        raise ValueError(f"origin: expected a 3-vector or an [H, W, 3] tensor, got {np.shape(origin)}")
    return mi.Vector3f(float(o[0]), float(o[1]), float(o[2]))
