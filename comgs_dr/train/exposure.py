"""Per-view exposure / white-balance compensation of step 1 (``RadianceConfig.exposure``).

Phone photos of one capture differ in exposure and white balance (auto exposure, auto
white balance, tone mapping per shot): one radiance field cannot match them all, so the
fit averages them and every view is off by its own colour transform. As is common for such
captures (NeRF-W's appearance codes, the per-image affine exposure of hierarchical 3DGS),
each training view ``i`` gets a learnt affine colour map of the rendered image,

    c' = (I + D_i) c + b_i          (D_i [3, 3], b_i [3]; 12 numbers per view, start at 0),

applied before the loss. The corrections are re-centred after every step (their mean over
the training views is the identity), so the radiance field keeps the views' average
exposure and a held-out view — which has no correction — is rendered at it.

Held-out views are scored raw (no correction: what ``psnr_test`` reports) and, as
``psnr_test_exposure``, colour-corrected as mip-NeRF 360 / Zip-NeRF evaluations do for
captures with varying exposure: an affine colour map fitted by least squares to each whole
held-out photo (:func:`psnr_exposure_fit`).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit
from comgs_dr.eval.metrics import psnr

KEY = "exposure"
PER_VIEW = 12          # D (3 x 3, row-major) then b (3)


class ViewExposure:
    """The per-view affine corrections of ``n_views`` training views and their Adam (which
    moves only the entries of the view that had a gradient this step)."""

    def __init__(self, n_views: int, lr: float, values: np.ndarray | None = None):
        self.n = int(n_views)
        self.opt = mi.ad.Adam(lr=lr, mask_updates=True)
        v = np.zeros(self.n * PER_VIEW, np.float32) if values is None else \
            np.asarray(values, np.float32).reshape(self.n * PER_VIEW)
        self.opt[KEY] = to_jit(mi.Float, v)

    # ---------------------------------------------------------------- apply
    def apply(self, color, i: int):
        """``color`` (TensorXf [H, W, 3]) through view ``i``'s correction (differentiable
        in both); views without one (held-out, ``i`` ≥ n) are returned unchanged."""
        if i >= self.n:
            return color
        h, w, c = color.shape
        if c != 3:
            raise ValueError(f"ViewExposure.apply: expected [H, W, 3] colour, got {color.shape}")
        e = self.opt[KEY]
        par = [dr.gather(mi.Float, e, dr.full(mi.UInt32, i * PER_VIEW + k, 1))
               for k in range(PER_VIEW)]
        flat = color.array
        pix = dr.arange(mi.UInt32, h * w)
        ch = [dr.gather(mi.Float, flat, pix * 3 + j) for j in range(3)]
        out = [ch[k] + par[9 + k] + par[3 * k] * ch[0] + par[3 * k + 1] * ch[1]
               + par[3 * k + 2] * ch[2] for k in range(3)]
        idx = dr.arange(mi.UInt32, h * w * 3)
        k = idx % 3
        p = idx // 3
        res = dr.select(k == 0, dr.gather(mi.Float, out[0], p),
                        dr.select(k == 1, dr.gather(mi.Float, out[1], p),
                                  dr.gather(mi.Float, out[2], p)))
        return mi.TensorXf(res, (h, w, 3))

    def apply_numpy(self, color: np.ndarray, i: int) -> np.ndarray:
        """Host version of :meth:`apply` for evaluation ([H, W, 3] float)."""
        if i >= self.n:
            return color
        m = self.matrix(i)
        return color @ (np.eye(3) + m[:, :3]).T + m[:, 3]

    # ---------------------------------------------------------------- step
    def step(self, lr: float) -> int:
        """One Adam step of the corrections (non-finite gradients zeroed, counted), then
        the re-centring."""
        g = dr.grad(self.opt[KEY])
        bad = int(dr.count(~dr.isfinite(g))[0]) if dr.width(g) else 0
        if bad:
            dr.set_grad(self.opt[KEY], dr.select(dr.isfinite(g), g, 0.0))
        self.opt.set_learning_rate({KEY: float(lr)})
        self.opt.step()
        v = self.values()
        v -= v.mean(0, keepdims=True)
        self.opt[KEY] = to_jit(mi.Float, v.ravel())
        return bad

    def zero_grad(self) -> None:
        dr.set_grad(self.opt[KEY], 0)

    # ---------------------------------------------------------------- state
    def values(self) -> np.ndarray:
        """[n, 12] host copy (D row-major, then b)."""
        return np.array(self.opt[KEY], np.float32).reshape(self.n, PER_VIEW)

    def matrix(self, i: int) -> np.ndarray:
        """[3, 4] (D | b) of view ``i``."""
        v = self.values()[i].astype(np.float64)
        return np.c_[v[:9].reshape(3, 3), v[9:]]

    def load(self, values: np.ndarray) -> None:
        """Install saved values (moments restart at zero)."""
        self.opt[KEY] = to_jit(mi.Float, np.asarray(values, np.float32).reshape(-1))
        self.opt.reset(KEY)

    def stats(self) -> dict:
        """Spread of the corrections: the largest |gain − 1| (diagonal of I + D) and |b|."""
        v = self.values()
        if not len(v):
            return {}
        return {"exposure_gain_dev": float(np.abs(v[:, [0, 4, 8]]).max()),
                "exposure_offset": float(np.abs(v[:, 9:]).max())}


def affine_fit(render: np.ndarray, photo: np.ndarray, fit_mask: np.ndarray) -> np.ndarray:
    """[3, 4] least-squares affine colour map ``photo ≈ M [render; 1]`` over ``fit_mask``
    pixels ([H, W] bool)."""
    x = render[fit_mask].reshape(-1, 3).astype(np.float64)
    y = photo[fit_mask][..., :3].reshape(-1, 3).astype(np.float64)
    a = np.c_[x, np.ones(len(x))]
    m, *_ = np.linalg.lstsq(a, y, rcond=None)
    return m.T


def psnr_exposure_fit(render: np.ndarray, photo: np.ndarray) -> float:
    """Held-out PSNR after a per-image affine colour correction (the "colour-corrected"
    metrics of mip-NeRF 360 / Zip-NeRF evaluations: 12 numbers fitted by least squares to
    the whole image, too few to fit anything but its exposure and white balance)."""
    h, w = render.shape[:2]
    m = affine_fit(render, photo, np.ones((h, w), bool))
    r = render.astype(np.float64)
    out = np.clip(r @ m[:, :3].T + m[:, 3], 0.0, 1.0).astype(np.float32)
    return psnr(out, photo[..., :3])
