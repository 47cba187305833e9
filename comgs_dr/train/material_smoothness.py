"""Edge-aware smoothness of the surfels' materials over their neighbour graph (step 2).

Not in the paper. Under one capture light, albedo, roughness and metallic of a surfel are
only weakly determined by its few pixels, and step 2 fits them independently: a
dielectric object gets spurious metallic and scattered low roughness, which the relit
object shows as sparkles and a paler colour. The prior ties each surfel to its nearest neighbours unless the step-1 colours differ (a texture
or material edge):

    L_smooth = Σ_(i,j) w_ij (|a_i − a_j|₁ / 3 + |r_i − r_j| + |m_i − m_j|) / Σ w_ij,
    w_ij = √(o_i o_j) · exp(−‖c_i − c_j‖² / (2 σ²)),

over the k nearest neighbours j of each surfel i within ``radius_factor`` × the median
nearest-neighbour distance; c the step-1 base colour (SH band 0, display sRGB), o the
opacity. Step 2 keeps the geometry fixed, so the graph is built once (scipy's cKDTree)
and the loss is a gather per step; it is the point-space counterpart of the image-space,
edge-aware material smoothness common in Gaussian inverse rendering. Its weight
(``MaterialConfig.lambda_smooth``) defaults to 0.1: under a known capture light it gives
the object its colour; under a learnt one it cannot resolve the albedo/light split (the
scale-aligned albedo PSNR falls on plain objects, rises on textured ones) but removes the
sparkles, and the composites gained 0.1–0.2 dB in the object+shadow region
(docs/composite.md, "Sparkles").
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.surfels.params import base_colour


def neighbour_pairs(means, colours, opacity, k: int = 8, sigma: float = 0.1,
                    radius_factor: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(i [M], j [M], w [M]) of the graph above from ``means`` [N, 3], ``colours`` [N, 3]
    (display sRGB) and ``opacity`` [N] in [0, 1]. Pairs of weight 0 are dropped; fewer
    than two surfels give empty arrays."""
    from scipy.spatial import cKDTree
    x = np.asarray(means, np.float64)                                       # [N, 3]
    c = np.asarray(colours, np.float64)                                     # [N, 3]
    o = np.clip(np.asarray(opacity, np.float64), 0.0, 1.0)                  # [N]
    n = x.shape[0]
    if x.ndim != 2 or x.shape[1] != 3 or c.shape != (n, 3) or o.shape != (n,):
        raise ValueError(f"neighbour_pairs: expected means [N, 3], colours [N, 3], opacity "
                         f"[N]; got {x.shape}, {c.shape}, {o.shape}")
    if not (np.isfinite(x).all() and np.isfinite(c).all() and np.isfinite(o).all()):
        raise ValueError("neighbour_pairs: non-finite means, colours or opacity")
    if k < 1 or sigma <= 0 or radius_factor <= 0:
        raise ValueError("neighbour_pairs: need k >= 1, sigma > 0 and radius_factor > 0")
    empty = (np.zeros(0, np.uint32), np.zeros(0, np.uint32), np.zeros(0, np.float32))
    if n < 2:
        return empty
    kk = min(k, n - 1)
    dist, idx = cKDTree(x).query(x, k=kk + 1)                               # [N, k+1]
    dist, idx = dist[:, 1:], idx[:, 1:]                                     # self dropped
    d0 = float(np.median(dist[:, 0]))
    i = np.repeat(np.arange(n), kk)                                         # [N·k]
    j = idx.ravel()
    w = np.sqrt(o[i] * o[j]) * np.exp(-((c[i] - c[j]) ** 2).sum(1) / (2 * sigma ** 2))
    w = np.where(dist.ravel() <= radius_factor * max(d0, 1e-12), w, 0.0)
    keep = w > 1e-6
    if not keep.any():
        return empty
    return i[keep].astype(np.uint32), j[keep].astype(np.uint32), w[keep].astype(np.float32)


def pairs_from_params(params, **kw) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``neighbour_pairs`` of a ``SurfelParams``: its means, SH band-0 colour, opacity."""
    d = params.to_numpy()
    sh = d["sh"].reshape(params.count, -1, 3)                               # [N, K, 3]
    colours = np.clip(base_colour(sh), 0.0, 1.0)                     # [N, 3]
    opacity = 1.0 / (1.0 + np.exp(-d["opacity_logit"]))                      # [N]
    return neighbour_pairs(d["means"], colours, opacity, **kw)


def material_smoothness(albedo: mi.Color3f, roughness: mi.Float, metallic: mi.Float,
                        i: mi.UInt32, j: mi.UInt32, w: mi.Float) -> mi.Float:
    """L_smooth (module docstring) of per-surfel materials over the pairs (i, j, w);
    0 for no pairs. Differentiable in the three materials."""
    if dr.width(w) == 0:
        return mi.Float(0.0)
    da = dr.abs(dr.gather(mi.Color3f, albedo, i) - dr.gather(mi.Color3f, albedo, j))
    dr_ = dr.abs(dr.gather(mi.Float, roughness, i) - dr.gather(mi.Float, roughness, j))
    dm = dr.abs(dr.gather(mi.Float, metallic, i) - dr.gather(mi.Float, metallic, j))
    per = (da[0] + da[1] + da[2]) / 3.0 + dr_ + dm                          # [M]
    return dr.sum(w * per) / dr.maximum(dr.sum(w), 1e-12)
