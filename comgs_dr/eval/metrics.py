"""Image and geometry metrics (numpy): PSNR, SSIM (3DGS convention), normal MAE, depth error."""
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import convolve1d

from comgs_dr.core.colorspace import LUMA, srgb_decode
from comgs_dr.surfels.params import base_colour


def psnr(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of [H, W, 3] images in [0, 1] (img clipped), optionally over a mask."""
    d = (np.clip(img[..., :3], 0, 1) - ref[..., :3]) ** 2
    mse = float(d[mask > 0.5].mean()) if mask is not None else float(d.mean())
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def ssim_map(img: np.ndarray, ref: np.ndarray, window: int = 11, sigma: float = 1.5) -> np.ndarray:
    """SSIM map [H, W, 3] with a Gaussian window and zero padding (the 3DGS/2DGS evaluation
    code; away from the border it equals scikit-image's ``structural_similarity``)."""
    x = np.clip(img[..., :3].astype(np.float64), 0, 1)
    y = ref[..., :3].astype(np.float64)
    g = np.exp(-((np.arange(window) - window // 2) ** 2) / (2 * sigma ** 2))
    g /= g.sum()

    def blur(a):
        a = convolve1d(a, g, axis=0, mode="constant")
        return convolve1d(a, g, axis=1, mode="constant")
    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


def ssim(img: np.ndarray, ref: np.ndarray, window: int = 11, sigma: float = 1.5) -> float:
    """Mean SSIM over all pixels of :func:`ssim_map` (zero-padded border included, as 3DGS)."""
    return float(ssim_map(img, ref, window, sigma).mean())


def normal_mae_deg(n: np.ndarray, n_gt: np.ndarray, mask: np.ndarray) -> float:
    """Mean angular error in degrees between normal maps [H, W, 3] over mask > 0.5."""
    a = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)
    b = n_gt / np.maximum(np.linalg.norm(n_gt, axis=-1, keepdims=True), 1e-8)
    cos = np.clip((a * b).sum(-1), -1, 1)[mask > 0.5]
    return float(np.degrees(np.arccos(cos)).mean()) if cos.size else float("nan")


def depth_errors(d: np.ndarray, d_gt: np.ndarray, mask: np.ndarray) -> dict:
    """Absolute and relative depth errors over mask > 0.5 (depth = ray distance)."""
    m = (mask > 0.5) & (d_gt > 0)
    if not m.any():
        return {"depth_mae": float("nan"), "depth_rel": float("nan")}
    e = np.abs(d[m] - d_gt[m])
    return {"depth_mae": float(e.mean()), "depth_rel": float((e / d_gt[m]).mean())}


def albedo_shading_split(params, min_opacity: float = 0.5) -> dict:
    """How a step-2 object split its capture's shading between the learnt light and the
    albedo, over its surfels of opacity > ``min_opacity`` (``params``: a SurfelParams with
    albedo): ``albedo_spread`` and ``step1_spread``, the standard deviations of the log
    luminance of the albedo and of the step-1 colour (SH band 0, display sRGB, decoded);
    ``slope``, the least-squares slope of the former on the latter (1: the albedo keeps all
    of the capture's shading; near 0 on a one-colour object: the light explains it; NaN
    when the step-1 colour does not vary); and
    ``albedo_median`` [3]."""
    d = params.to_numpy()
    opaque = 1.0 / (1.0 + np.exp(-d["opacity_logit"].astype(np.float64))) > min_opacity
    if opaque.sum() < 2:
        raise ValueError(f"albedo_shading_split: {int(opaque.sum())} surfels above opacity "
                         f"{min_opacity}; need 2")
    a = d["albedo"][opaque].astype(np.float64)
    c = np.asarray(srgb_decode(np.clip(base_colour(d["sh"][opaque]), 1e-3, 1.0)), np.float64)
    la, lc = (np.log(np.maximum(x @ LUMA, 1e-4)) for x in (a, c))
    var = float(lc.var())        # a one-colour step 1 (a synthetic run): no slope to read
    slope = float(np.mean((lc - lc.mean()) * (la - la.mean())) / var) if var > 1e-12 else np.nan
    return {"albedo_spread": float(la.std()), "step1_spread": float(lc.std()),
            "slope": slope, "albedo_median": np.median(a, 0)}
