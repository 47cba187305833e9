"""What a user looks at in a composite: the object and its shadow, scored and drawn.

A full-image PSNR is dominated by the scene, which every variant shares; the insertion
lives in a few percent of the pixels. With the composition dataset's path-traced truth
(``gt``: the composite, ``empty``: the scene without the object, ``mask``: the object's
pixels), this module scores a render in

* the **object+shadow region**: the object's pixels and the truth's shadow pixels
  (truth / empty < ``SHADOW_THRESH`` in luminance) grown by ``GROW`` px: PSNR there;
* the **shadow's darkness**: the mean of render / empty over the truth's shadow pixels,
  against the truth's (the depth ratio (1 − ours) / (1 − truth): 1 is as dark as the truth);
  and the same over the area (``shadow_depth_area``: Σ render / Σ empty over those pixels).
  The per-pixel mean charges a reconstruction's blur of the scene's texture to the shadow:
  a blurred texture's ratio to the sharp one averages above 1 even where the mean level is
  right (the default demo's paste, which has no shadow, reads 1.094 per pixel and 1.006 over
  the area in the truth's shadow pixels), so both are reported;
* the **object's colour**: its mean linear colour per channel over the truth's object
  pixels, divided by the truth's;

and draws full-size crops of the shadow and of the object side by side, and the darkness
along a line through the shadow. Images are the 8-bit sRGB files the renders write; the
truth's ``empty`` is linear (EXR).
"""
from __future__ import annotations

import io

import numpy as np
from PIL import Image, ImageDraw
from scipy.ndimage import binary_dilation

from comgs_dr.core.colorspace import luminance, srgb_decode

def _u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(np.nan_to_num(img), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


SHADOW_THRESH = 0.7       # truth / empty luminance below this: a shadow pixel of the truth
GROW = 2                  # px the object+shadow region is grown by (penumbra, silhouette)


def regions(gt_lin: np.ndarray, empty_lin: np.ndarray, obj: np.ndarray):
    """(shadow [H, W] bool, region [H, W] bool, truth ratio [H, W]) of one frame."""
    le = luminance(empty_lin)
    ratio = luminance(gt_lin) / np.maximum(le, 1e-6)
    shadow = (ratio < SHADOW_THRESH) & ~obj & (le > 1e-3)
    region = binary_dilation(shadow | obj, iterations=GROW)
    return shadow, region, ratio


def frame_scores(pred: np.ndarray, gt: np.ndarray, empty_lin: np.ndarray, obj: np.ndarray):
    """Per-frame sums (pooled by :func:`summarise`): ``pred``/``gt`` [H, W, 3] sRGB in [0, 1]."""
    gl, pl = srgb_decode(gt), srgb_decode(pred)
    shadow, region, ratio = regions(gl, empty_lin, obj)
    le = np.maximum(luminance(empty_lin), 1e-6)
    mse = float(np.mean((pred[region] - gt[region]) ** 2)) if region.any() else float("nan")
    return {"region_pixels": int(region.sum()), "region_mse": mse,
            "shadow_pixels": int(shadow.sum()),
            "shadow_sum_ours": float((luminance(pl) / le)[shadow].sum()),
            "shadow_sum_truth": float(ratio[shadow].sum()),
            "shadow_lum_ours": float(luminance(pl)[shadow].sum()),
            "shadow_lum_truth": float(luminance(gl)[shadow].sum()),
            "shadow_lum_empty": float(luminance(empty_lin)[shadow].sum()),
            "object_pixels": int(obj.sum()),
            "object_sum_ours": pl[obj].sum(0).tolist(), "object_sum_truth": gl[obj].sum(0).tolist()}


def summarise(frames: list[dict]) -> dict:
    """Region PSNR (mean over frames), shadow darkness and object colour (pooled pixels)."""
    mses = [f["region_mse"] for f in frames if f["region_pixels"]]
    out = {"psnr_region": float(np.mean([-10 * np.log10(max(m, 1e-12)) for m in mses]))
           if mses else None}
    n = sum(f["shadow_pixels"] for f in frames)
    if n:
        s = sum(f["shadow_sum_ours"] for f in frames) / n
        t = sum(f["shadow_sum_truth"] for f in frames) / n
        out.update(shadow_ratio=s, shadow_ratio_truth=t,
                   shadow_depth=(1 - s) / max(1 - t, 1e-6), shadow_pixels=n)
        e = sum(f.get("shadow_lum_empty", 0.0) for f in frames)
        if e > 0 and all("shadow_lum_ours" in f for f in frames):
            sa = sum(f["shadow_lum_ours"] for f in frames) / e
            ta = sum(f["shadow_lum_truth"] for f in frames) / e
            out.update(shadow_ratio_area=sa, shadow_ratio_truth_area=ta,
                       shadow_depth_area=(1 - sa) / max(1 - ta, 1e-6))
    if sum(f["object_pixels"] for f in frames):
        ours = np.sum([f["object_sum_ours"] for f in frames], 0)
        truth = np.sum([f["object_sum_truth"] for f in frames], 0)
        out["object_colour_ratio"] = (ours / np.maximum(truth, 1e-9)).tolist()
    return out


# ----------------------------------------------------------------------------- figures

def _box(mask: np.ndarray, pad: int, min_side: int = 12):
    """(y0, y1, x0, x1) around ``mask`` (padded, at least ``min_side``), or None."""
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return None
    h, w = mask.shape
    cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
    half = max(ys.max() - ys.min(), xs.max() - xs.min(), min_side) / 2 + pad
    y0, x0 = int(max(0, cy - half)), int(max(0, cx - half))
    return y0, int(min(h, cy + half + 1)), x0, int(min(w, cx + half + 1))


def crops_figure(gt: np.ndarray, preds: dict, obj: np.ndarray, shadow: np.ndarray,
                 height: int = 160) -> Image.Image:
    """Rows: the shadow, the object; columns: truth | each render; nearest-neighbour
    enlarged to ``height`` px, so every pixel is seen."""
    cols = [("truth", gt)] + list(preds.items())
    rows = [(n, b) for n, b in (("shadow", _box(shadow, 3)), ("object", _box(obj, 3)))
            if b is not None]
    if not rows:
        raise ValueError("crops_figure: the truth has neither shadow nor object pixels")
    bar, gap = 14, 4
    tiles = []
    for label, (y0, y1, x0, x1) in rows:
        s = max(1, height // max(y1 - y0, 1))
        tiles.append([(f"{label}: {c}", Image.fromarray(_u8(img[y0:y1, x0:x1])).resize(
            ((x1 - x0) * s, (y1 - y0) * s), Image.NEAREST)) for c, img in cols])
    W = max(sum(t.width + gap for _, t in row) for row in tiles)
    H = sum(max(t.height for _, t in row) + bar for row in tiles)
    sheet = Image.new("RGB", (W, H), "white")
    draw, y = ImageDraw.Draw(sheet), 0
    for row in tiles:
        x = 0
        for label, t in row:
            sheet.paste(t, (x, y + bar))
            draw.text((x + 2, y + 1), label, fill=(0, 0, 0))
            x += t.width + gap
        y += max(t.height for _, t in row) + bar
    return sheet


def shadow_line(shadow: np.ndarray, extend: float = 0.6, samples: int = 96):
    """(ys, xs) pixel coordinates along the shadow's principal axis through its centroid,
    extended by ``extend`` × its half-length on each side (into the lit scene), or None."""
    ys, xs = np.nonzero(shadow)
    if len(ys) < 3:
        return None
    p = np.c_[ys, xs].astype(np.float64)
    c = p.mean(0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    a = vt[0]
    half = np.abs((p - c) @ a).max() * (1 + extend) + 2
    t = np.linspace(-half, half, samples)
    q = c[None] + t[:, None] * a[None]
    h, w = shadow.shape
    keep = (q[:, 0] >= 0) & (q[:, 0] <= h - 1) & (q[:, 1] >= 0) & (q[:, 1] <= w - 1)
    q = np.rint(q[keep]).astype(int)
    return q[:, 0], q[:, 1]


def profile_png(gt: np.ndarray, empty_lin: np.ndarray, preds: dict, shadow: np.ndarray) -> bytes | None:
    """PNG bytes: luminance / the truth's empty scene along :func:`shadow_line` for the truth
    and each render (1: unshadowed), with the line drawn on the truth; None without a shadow."""
    line = shadow_line(shadow)
    if line is None:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ys, xs = line
    le = np.maximum(luminance(empty_lin), 1e-6)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(9, 3.2), gridspec_kw={"width_ratios": [1, 2.4]})
    ax0.imshow(np.clip(gt, 0, 1), interpolation="nearest")
    ax0.plot(xs, ys, "c-", lw=1)
    ax0.set_axis_off()
    ax0.set_title("truth, and the line", fontsize=8)
    d = np.r_[0, np.cumsum(np.hypot(np.diff(ys), np.diff(xs)))]
    for name, img in [("truth", gt)] + list(preds.items()):
        r = luminance(srgb_decode(img))[ys, xs] / le[ys, xs]
        ax1.plot(d, r, "k-" if name == "truth" else "-", lw=2 if name == "truth" else 1.2,
                 label=name)
    ax1.axhline(1.0, color="0.6", lw=0.8, ls="--")
    ax1.set_xlabel("px along the shadow's axis")
    ax1.set_ylabel("luminance / truth's empty scene")
    ax1.legend(fontsize=7)
    ax1.set_ylim(0, max(1.3, ax1.get_ylim()[1]))
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()
