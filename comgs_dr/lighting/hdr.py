"""HDR expansion of completed panoramas, light extraction and baseline panorama completion.

Paper, "Lighting Estimation" and Appendix "Details of Lighting Estimation": the completion
model generates LDR panoramas at EV ∈ {0, −2.5, −5} that are fused into one HDR
environment map. This module holds everything around that model that needs no network.

**Exposure model.** Linear HDR radiance ``hdr`` seen at exposure value ``ev`` gives the LDR
panorama ::

    ldr = clip(srgb_encode(hdr · 2**ev), 0, 1)

with the IEC 61966-2-1 sRGB transfer function. ``unexpose(ldr, ev) = srgb_decode(ldr) / 2**ev``
inverts it wherever ``ldr < 1`` (it clips ``ldr`` to [0, 1] first). At EV 0 the white level
is radiance 1; at EV −5 it is 2**5 = 32.

**Bracket fusion** (``fuse_brackets``): start from the brightest exposure's un-exposed
radiance; wherever that exposure nears saturation (max channel above ``sat − width``) blend
towards the next darker exposure with a smoothstep weight that reaches 1 at ``sat``, and
repeat down the bracket. The weight is C¹, so the torch path is differentiable everywhere
(``gradcheck`` passes). **Saturation limit:** nothing above the darkest exposure's white
level can be recovered, i.e. radiance is clipped to 2**5 × the EV-0 white level = 32 for
EV −5 (a 1e3 sun comes back as 32 and its power is underestimated accordingly).

``expose``, ``unexpose``, ``srgb_encode``, ``srgb_decode`` and ``fuse_brackets`` accept NumPy
arrays or torch tensors (dispatch on the input type; the torch path is autograd-friendly).

**Lights** (``extract_lights``): hysteresis thresholding of luminance on the equirect map
(seeds above a solid-angle-weighted quantile, grown into connected pixels above a lower
quantile and above a fraction of the region's peak), labelled
with 8-connectivity, merged across the u = 0/1 seam and across the poles, and integrated with
exact pixel solid angles. Directions follow the Blender Z-up equirect convention of
``lighting.envmap``: u = 0.5 − atan2(y, x)/2π, v = acos(z)/π, v = 0 the top row.

**Baselines** (``mean_fill``, ``push_pull_fill``, ``sh_fill``): non-learned completions of a
partial panorama ``rgb`` [H, W, C] with ``mask`` [H, W] (1 = observed). Observed pixels are
returned unchanged; holes may hold anything, NaN included.
"""
from __future__ import annotations

from math import factorial, pi, sqrt

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from comgs_dr.core.colorspace import LUMA, as_float, is_torch, srgb_decode, srgb_encode
from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles

__all__ = ["expose", "unexpose", "fuse_brackets",
           "DEFAULT_EVS", "saturation_limit",
           "label_equirect", "area_resize_equirect", "extract_lights", "real_sh_basis", "mean_fill",
           "push_pull_fill", "sh_fill", "check_ldr_mask", "SAT", "seen_sky_fraction",
           "OPEN_SKY_WARN",
           "clipped_sky_fraction", "SEEN_SKY_WARN", "CLIPPED_SKY_WARN"]

DEFAULT_EVS = (0.0, -2.5, -5.0)
SAT = 0.98                 # EV-0 max channel at/above which a pixel counts as clipped
CLIPPED_SKY_WARN = 0.3     # clipped_sky_fraction above it: the light inside is not readable
SEEN_SKY_WARN = 0.25       # seen_sky_fraction below it: the lights above are the completion's guess
OPEN_SKY_WARN = 0.1        # open sky (a learned background) below it, the upper hemisphere seen:
                           # it is surfels (a forward-facing capture; views that look around
                           # leave well over half of it open)


# ---------------------------------------------------------------------------------------
# Exposure model (NumPy or torch)


def expose(hdr, ev: float):
    """LDR panorama of linear radiance ``hdr`` at exposure ``ev``: clip(sRGB(hdr·2^ev), 0, 1)."""
    return srgb_encode(as_float(hdr) * 2.0 ** float(ev)).clip(0.0, 1.0)


def unexpose(ldr, ev: float):
    """Radiance of an LDR panorama at exposure ``ev`` (exact inverse where ldr < 1)."""
    return srgb_decode(as_float(ldr).clip(0.0, 1.0)) / 2.0 ** float(ev)


def saturation_limit(evs=DEFAULT_EVS) -> float:
    """Largest radiance a fused bracket can represent: the darkest exposure's white level."""
    return 2.0 ** -min(float(e) for e in evs)


def _lookup(ldrs: dict, ev: float):
    for key, val in ldrs.items():
        if abs(float(key) - float(ev)) < 1e-6:
            return as_float(val)
    raise ValueError(f"fuse_brackets: no LDR panorama for EV {ev} (have {sorted(ldrs)})")


def fuse_brackets(ldrs: dict, evs=DEFAULT_EVS, sat: float = 0.95, width: float = 0.1,
                  measure: str = "max"):
    """Fuse LDR panoramas ``{ev: [H, W, 3]}`` into one linear HDR map [H, W, 3].

    Brightest exposure first; where it nears saturation its radiance is replaced by the next
    darker exposure's, with weight smoothstep((s − (sat − width)) / width), where s is the
    max channel (``measure="max"``: any clipped channel counts) or the Rec. 709 luminance
    (``"luma"``) of the brighter LDR. NumPy in -> NumPy out, torch in -> torch out
    (differentiable). Radiance above ``saturation_limit(evs)`` cannot be recovered.
    """
    if not evs:
        raise ValueError("fuse_brackets: evs is empty")
    if not 0.0 < width <= sat <= 1.0:
        raise ValueError(f"fuse_brackets: need 0 < width <= sat <= 1, got sat={sat}, "
                         f"width={width}")
    if measure not in ("max", "luma"):
        raise ValueError(f"fuse_brackets: measure must be 'max' or 'luma', got {measure!r}")
    evs = sorted((float(e) for e in evs), reverse=True)
    imgs = [_lookup(ldrs, e) for e in evs]
    shape = tuple(imgs[0].shape)
    if len(shape) != 3 or shape[-1] != 3:
        raise ValueError(f"fuse_brackets: panoramas must be [H, W, 3], got {shape}")
    if any(tuple(im.shape) != shape for im in imgs):
        raise ValueError(f"fuse_brackets: shapes differ: {[tuple(i.shape) for i in imgs]}")
    hdr = unexpose(imgs[0], evs[0])
    for brighter, img, ev in zip(imgs[:-1], imgs[1:], evs[1:]):
        b = brighter.clip(0.0, 1.0)
        if measure == "max":
            s = b.amax(-1) if is_torch(b) else b.max(-1)
        else:
            s = b[..., 0] * LUMA[0] + b[..., 1] * LUMA[1] + b[..., 2] * LUMA[2]
        t = ((s - (sat - width)) / width).clip(0.0, 1.0)
        w = (t * t * (3.0 - 2.0 * t))[..., None]
        hdr = hdr + w * (unexpose(img, ev) - hdr)
    return hdr


# ---------------------------------------------------------------------------------------
# Equirect geometry


def _overlap(edges_in, edges_out) -> np.ndarray:
    """[n_out, n_in] overlap lengths of 1D cells given by increasing edge arrays."""
    lo = np.maximum(edges_out[:-1, None], edges_in[None, :-1])
    hi = np.minimum(edges_out[1:, None], edges_in[None, 1:])
    return np.maximum(hi - lo, 0.0)


def area_resize_equirect(env, h: int, w: int) -> np.ndarray:
    """Resample an [H, W, C] equirect map to [h, w, C] by solid-angle-weighted area averaging.

    Separable and exact for any sizes: a target pixel is the mean over its solid angle of the
    piecewise-constant source (columns weighted by overlap in u, rows by overlap in cos θ), so
    Σ L dω is preserved. float64 out."""
    env = np.asarray(env, np.float64)
    if env.ndim != 3 or h < 1 or w < 1:
        raise ValueError(f"area_resize_equirect: need an [H, W, C] map and h, w >= 1, got "
                         f"{env.shape} -> ({h}, {w})")
    hin, win = env.shape[:2]
    if (hin, win) == (h, w):
        return env.copy()
    cu = _overlap(np.linspace(0, 1, win + 1), np.linspace(0, 1, w + 1))           # [w, W]
    cv = _overlap(-np.cos(np.linspace(0, pi, hin + 1)), -np.cos(np.linspace(0, pi, h + 1)))
    cu /= cu.sum(1, keepdims=True)
    cv /= cv.sum(1, keepdims=True)                                                # [h, H]
    return np.einsum("ij,jkc,lk->ilc", cv, env, cu, optimize=True)


def label_equirect(mask) -> tuple[np.ndarray, int]:
    """8-connected components of an [H, W] equirect mask, merged across the u = 0/1 seam
    and across each pole (top/bottom-row pixel x touches pixel x + W/2). Labels are 1..n."""
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    lab, n = ndimage.label(mask, structure=np.ones((3, 3), int))
    if n == 0:
        return lab, 0
    pairs = []
    left, right = lab[:, 0], lab[:, -1]
    for dy in (-1, 0, 1):
        a, b = left[max(0, dy):h + min(0, dy)], right[max(0, -dy):h + min(0, -dy)]
        pairs.append(np.stack([a, b], -1))
    for row in (lab[0], lab[-1]):
        pairs.append(np.stack([row, np.roll(row, -(w // 2))], -1))
    p = np.concatenate(pairs)
    p = p[(p[:, 0] > 0) & (p[:, 1] > 0)]
    g = coo_matrix((np.ones(len(p)), (p[:, 0], p[:, 1])), shape=(n + 1, n + 1))
    _, comp = connected_components(g, directed=False)
    keep = np.unique(comp[1:])                       # components that hold real labels
    remap = np.zeros(comp.max() + 1, int)
    remap[keep] = np.arange(1, len(keep) + 1)
    table = np.concatenate([[0], remap[comp[1:]]])
    return table[lab], len(keep)


def _weighted_quantile(x, wgt, q: float) -> float:
    """Smallest value of ``x`` whose weighted CDF reaches ``q``."""
    order = np.argsort(x, kind="stable")
    cdf = np.cumsum(wgt[order])
    return float(x[order][min(np.searchsorted(cdf, q * cdf[-1]), len(x) - 1)])


def extract_lights(hdr_equirect, k: int = 3, threshold_quantile: float = 0.999,
                   grow_quantile: float | None = None,
                   peak_ratio: float = 0.01) -> list[dict]:
    """Up to ``k`` brightest compact light sources of a linear [H, W, 3] equirect map.

    Quantiles are solid-angle weighted (a sun near a pole covers many pixels but little
    sphere). Seeds are pixels whose luminance is ≥ the ``threshold_quantile`` quantile; a
    light is a connected component (``label_equirect``) of pixels ≥ the ``grow_quantile``
    quantile (default 1 − 10·(1 − q), ≥ 0.5) and ≥ ``peak_ratio`` × the peak of its grown
    region (sheds circumsolar glow) that holds a seed, so anti-aliased edges count toward
    its power. Lights brighter than ~(1 − q)·4π sr of the sphere at full radiance
    saturate both quantiles and lose their partially covered edge pixels. Each light: ``direction`` (unit, luminance·dω-weighted mean), ``solid_angle``
    (sr), ``rgb_power`` = Σ L dω, ``mean_radiance`` = power / solid angle and
    ``peak_luminance`` (its brightest pixel); sorted by
    luminance power, largest first. An all-black map gives [].
    """
    img = np.asarray(hdr_equirect, np.float64)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise ValueError(f"extract_lights: expected an [H, W, 3] map, got {img.shape}")
    if not np.isfinite(img).all():
        raise ValueError("extract_lights: map has NaN/Inf values")
    if not 0.0 < threshold_quantile < 1.0 or k < 1:
        raise ValueError("extract_lights: need 0 < threshold_quantile < 1 and k >= 1")
    h, w, _ = img.shape
    lum = img @ LUMA
    if lum.max() <= 0.0:
        return []
    gq = max(0.5, 1.0 - 10.0 * (1.0 - threshold_quantile)) if grow_quantile is None \
        else grow_quantile
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w)).ravel()
    t_seed = _weighted_quantile(lum.ravel(), dw, threshold_quantile)
    t_grow = min(_weighted_quantile(lum.ravel(), dw, gq), t_seed)
    seeds = (lum >= t_seed) & (lum > 0)
    grown = (lum >= t_grow) & (lum > 0)
    lab, n = label_equirect(grown)
    peak = np.zeros(n + 1)
    np.maximum.at(peak, lab.ravel(), lum.ravel())
    lab, n = label_equirect(grown & (lum >= peak_ratio * peak[lab]))  # drop glow/halo
    ids = np.unique(lab[seeds])
    ids = ids[ids > 0]
    flat = lab.ravel()
    power = np.stack([np.bincount(flat, img[..., c].ravel() * dw, n + 1) for c in range(3)], -1)
    area = np.bincount(flat, dw, n + 1)
    wl = lum.ravel() * dw
    d = equirect_directions(h, w).reshape(-1, 3)
    dsum = np.stack([np.bincount(flat, d[:, c] * wl, n + 1) for c in range(3)], -1)
    top = np.zeros(n + 1)
    np.maximum.at(top, flat, lum.ravel())
    lights = []
    for i in ids:
        direction = dsum[i] / max(np.linalg.norm(dsum[i]), 1e-300)
        lights.append({"direction": direction, "solid_angle": float(area[i]),
                       "rgb_power": power[i].copy(), "mean_radiance": power[i] / area[i],
                       "peak_luminance": float(top[i])})
    lights.sort(key=lambda l: -float(l["rgb_power"] @ LUMA))
    return lights[:k]


# ---------------------------------------------------------------------------------------
# Baseline completions

def check_ldr_mask(ldr, mask, who: str) -> tuple[np.ndarray, np.ndarray]:
    """(ldr clipped to [0, 1] float64 [H, W, 3], observed bool [H, W]) from an EV-0 LDR
    panorama and its mask ([H, W] or [H, W, 1], > ½ = observed); ValueError naming ``who``
    for other shapes or NaN/Inf."""
    ldr = np.asarray(ldr, np.float64)
    mask = np.asarray(mask, np.float64)
    mask = mask[..., 0] if mask.ndim == 3 else mask
    if ldr.ndim != 3 or ldr.shape[-1] != 3 or mask.shape != ldr.shape[:2]:
        raise ValueError(f"{who}: need an [H, W, 3] EV-0 panorama and an [H, W] mask, got "
                         f"{ldr.shape} and {mask.shape}")
    if not (np.isfinite(ldr).all() and np.isfinite(mask).all()):
        raise ValueError(f"{who}: the panorama or the mask holds NaN/Inf values")
    return np.clip(ldr, 0.0, 1.0), mask > 0.5


def clipped_sky_fraction(ldr, mask, sat: float = SAT) -> float:
    """Solid-angle fraction of the observed upper hemisphere (elevation > 0) whose EV-0 max
    channel is clipped (≥ ``sat``); 0 when none of it is observed.

    Above ``CLIPPED_SKY_WARN`` one exposure no longer says where the light is nor how strong:
    a sky blown out around the sun is one clipped region whose centroid is the sky's, and the
    brackets and the head only see its rim. Good captures of a clear sky stay well below the
    threshold; a broad dawn glow or an over-exposed sunset exceeds it."""
    ldr, seen = check_ldr_mask(ldr, mask, "clipped_sky_fraction")
    h, w = seen.shape
    up = np.broadcast_to(equirect_directions(h, w)[..., 2] > 0, (h, w))
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    sky = seen & up
    area = float((sky * dw).sum())
    if area <= 0.0:
        return 0.0
    return float(((sky & (ldr.max(-1) >= sat)) * dw).sum() / area)


def seen_sky_fraction(mask) -> float:
    """Solid-angle fraction of the upper hemisphere (elevation > 0; sky or ceiling, where the
    lights usually are) that is observed (mask > ½) in an equirect mask [H, W].

    Below ``SEEN_SKY_WARN`` no light above the placement was seen, so the head has nothing to
    restore and the sun's direction and power are the completion's guess (as for a capture
    whose views all look down at the ground)."""
    m = np.asarray(mask, np.float64)
    m = m[..., 0] if m.ndim == 3 and m.shape[-1] == 1 else m
    if m.ndim != 2 or not np.isfinite(m).all():
        raise ValueError(f"seen_sky_fraction: need a finite [H, W] or [H, W, 1] mask, got "
                         f"shape {np.shape(mask)}")
    h, w = m.shape
    up = np.broadcast_to(equirect_directions(h, w)[..., 2] > 0, (h, w))
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    area = float((up * dw).sum())
    return float(((up & (m > 0.5)) * dw).sum() / area) if area > 0 else 0.0


def _check_fill(rgb, mask, name: str):
    """Validate inputs; returns (float64 image with holes zeroed, bool mask, out dtype)."""
    rgb = np.asarray(rgb)
    mask = np.asarray(mask)
    if rgb.ndim != 3 or rgb.shape[-1] < 1:
        raise ValueError(f"{name}: rgb must be [H, W, C], got shape {rgb.shape}")
    if mask.ndim == 3 and mask.shape[-1] == 1:
        mask = mask[..., 0]
    if mask.shape != rgb.shape[:2]:
        raise ValueError(f"{name}: mask must be [H, W] = {rgb.shape[:2]}, got {mask.shape}")
    mask = mask.astype(np.float64)
    if not np.isfinite(mask).all() or mask.min() < 0.0 or mask.max() > 1.0:
        raise ValueError(f"{name}: mask values must lie in [0, 1] (1 = observed)")
    m = mask > 0.5
    if not m.any():
        raise ValueError(f"{name}: zero coverage (mask is all 0), nothing to complete from")
    dtype = rgb.dtype if np.issubdtype(rgb.dtype, np.floating) else np.float64
    img = rgb.astype(np.float64)
    if not np.isfinite(img[m]).all():
        raise ValueError(f"{name}: observed pixels contain NaN/Inf")
    img[~m] = 0.0
    return img, m, dtype


def _finish(rgb, fill, m, dtype):
    out = np.where(m[..., None], np.asarray(rgb), fill).astype(dtype)
    return out


def mean_fill(rgb, mask) -> np.ndarray:
    """Fill holes with the solid-angle-weighted mean of the observed pixels."""
    img, m, dtype = _check_fill(rgb, mask, "mean_fill")
    wgt = m * pixel_solid_angles(*m.shape)
    mean = (img * wgt[..., None]).sum((0, 1)) / wgt.sum()
    return _finish(rgb, np.broadcast_to(mean, img.shape), m, dtype)


def _down(x):
    """2×2 block sums of [h, w, ...] (zero-padded to even; a size-1 axis is not halved)."""
    h, w = x.shape[:2]
    if h > 1:
        x = np.pad(x, [(0, h % 2)] + [(0, 0)] * (x.ndim - 1))
        x = x[0::2] + x[1::2]
    if w > 1:
        x = np.pad(x, [(0, 0), (0, w % 2)] + [(0, 0)] * (x.ndim - 2))
        x = x[:, 0::2] + x[:, 1::2]
    return x


def _up(c, h: int, w: int):
    """Bilinear upsampling of a coarse [h', w', C] level to [h, w, C]: rows clamp, columns
    wrap (equirect u is periodic); fine pixel i sits at coarse coordinate i/2 − 1/4."""
    hc, wc = c.shape[:2]
    if hc != h:
        y = np.arange(h) / 2.0 - 0.25
        y0 = np.floor(y).astype(int)
        f = (y - y0)[:, None, None]
        c = (1 - f) * c[np.clip(y0, 0, hc - 1)] + f * c[np.clip(y0 + 1, 0, hc - 1)]
    if wc != w:
        x = np.arange(w) / 2.0 - 0.25
        x0 = np.floor(x).astype(int)
        f = (x - x0)[None, :, None]
        c = (1 - f) * c[:, x0 % wc] + f * c[:, (x0 + 1) % wc]
    return c


def push_pull_fill(rgb, mask) -> np.ndarray:
    """Pyramid push-pull: push = 2×2 solid-angle-weighted sums of observed colour, observed
    weight and total weight down to 1×1; pull = from the top, each level's colour is
    α·(observed mean) + (1 − α)·(upsampled coarser fill), α = observed fraction of its
    solid angle. Upsampling wraps in u, so the fill is continuous across the seam."""
    img, m, dtype = _check_fill(rgb, mask, "push_pull_fill")
    area = np.broadcast_to(pixel_solid_angles(*m.shape), m.shape)
    area = area / area.max()
    wgt = m * area
    levels = [(img * wgt[..., None], wgt, area)]
    while levels[-1][1].shape != (1, 1):
        levels.append(tuple(_down(x) for x in levels[-1]))
    sc, sw, _ = levels[-1]
    fill = sc / sw[..., None]
    for sc, sw, sa in reversed(levels[:-1]):
        up = _up(fill, *sw.shape)
        alpha = np.where(sa > 0, sw / np.where(sa > 0, sa, 1.0), 0.0)[..., None]
        colour = sc / np.maximum(sw, 1e-300)[..., None]
        fill = alpha * colour + (1.0 - alpha) * up
    return _finish(rgb, fill, m, dtype)


def real_sh_basis(dirs, order: int) -> np.ndarray:
    """Orthonormal real spherical harmonics up to degree ``order`` at [N, 3] unit directions
    -> [N, (order + 1)²], index l² + l + m (m < 0: sin |m|φ, m > 0: cos mφ)."""
    if int(order) != order or order < 0:
        raise ValueError(f"real_sh_basis: order must be an integer >= 0, got {order}")
    d = np.asarray(dirs, np.float64)
    z = np.clip(d[:, 2], -1.0, 1.0)
    phi = np.arctan2(d[:, 1], d[:, 0])
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    out = np.zeros((len(d), (order + 1) ** 2))
    pmm = np.ones_like(z)
    for m in range(order + 1):
        if m > 0:
            pmm = -(2 * m - 1) * s * pmm                     # P_m^m
        p_prev, p = None, pmm
        for l in range(m, order + 1):
            if l == m + 1:
                p_prev, p = p, z * (2 * m + 1) * pmm
            elif l > m + 1:
                p_prev, p = p, ((2 * l - 1) * z * p - (l + m - 1) * p_prev) / (l - m)
            k = sqrt((2 * l + 1) / (4 * pi) * factorial(l - m) / factorial(l + m))
            if m == 0:
                out[:, l * l + l] = k * p
            else:
                out[:, l * l + l + m] = sqrt(2) * k * np.cos(m * phi) * p
                out[:, l * l + l - m] = sqrt(2) * k * np.sin(m * phi) * p
    return out


def sh_fill(rgb, mask, order: int = 2, ridge: float = 1e-6) -> np.ndarray:
    """Solid-angle-weighted least-squares fit of real SH up to ``order`` on the observed
    directions (ridge λ = ``ridge`` × mean diagonal of the normal matrix), evaluated in the
    holes and clamped ≥ 0."""
    img, m, dtype = _check_fill(rgb, mask, "sh_fill")
    h, w, _ = img.shape
    basis = real_sh_basis(equirect_directions(h, w).reshape(-1, 3), order)
    wgt = (m * pixel_solid_angles(h, w)).ravel()
    obs = wgt > 0
    a, wo = basis[obs], wgt[obs][:, None]
    gram = a.T @ (a * wo)
    lam = ridge * np.trace(gram) / len(gram)
    coef = np.linalg.solve(gram + lam * np.eye(len(gram)),
                           a.T @ (img.reshape(-1, img.shape[-1])[obs] * wo))
    fill = np.maximum(basis @ coef, 0.0).reshape(img.shape)
    return _finish(rgb, fill, m, dtype)
