"""2DGS adaptive density control: clone / split / prune / opacity reset.

Works on numpy copies (every ~100 iterations), keeping the surfel parameters and
the Adam moments of :class:`drjit.opt.Adam` aligned: surviving surfels keep their
moments, new ones (clones, split children) start with zero first moments and their
source's second moments (3DGS/2DGS zero both: see :func:`_remap_optimizer`), pruned
ones are dropped.

View-space gradient. 3DGS accumulates ‖∂L/∂μ_2D‖ of the projected mean in NDC
units. A ray tracer has no projected mean, so we use the world-space gradient's
component orthogonal to the viewing direction, scaled to NDC: for a pinhole
camera a lateral world displacement δ at distance z moves the projection by
δ·f/z pixels = δ/(z·tan(fov_x/2)) NDC units, hence
‖∂L/∂μ_ndc‖ = ‖(∂L/∂μ)_⊥‖ · z · tan(fov_x/2).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from comgs_dr.surfels.io import quat_to_matrix
from comgs_dr.surfels.params import SurfelParams, field_from_numpy, field_to_numpy


@dataclasses.dataclass
class DensityConfig:
    """Schedule and thresholds (2DGS defaults rescaled to short CPU runs)."""
    start: int = 300                 # first densification iteration (2DGS: 500)
    stop: int = 2000                 # last densification iteration (2DGS: 15000)
    until: float = 1.0               # ... and never after this fraction of the run (its or time)
    interval: int = 100
    grad_threshold: float = 2e-4     # mean NDC-space gradient norm that triggers densification
    percent_dense: float = 0.01      # clone if max scale ≤ this · scene extent, else split
    split_children: int = 2
    min_opacity: float = 0.005       # prune below
    max_scale: float = 0.1           # prune if max scale > this · scene extent (after reset)
    opacity_reset_interval: int = 1000
    opacity_reset_value: float = 0.01
    max_fraction: float = 0.05       # densify at most this fraction of the surfels per step
    max_surfels: int = 300_000       # never grow beyond (densify the largest gradients first)
    clone_opacity_split: bool = True  # clone and source share the opacity (image unchanged)






class DensityController:
    """Accumulates view-space gradients and edits surfels (+ optimiser state)."""

    def __init__(self, cfg: DensityConfig, count: int, extent: float):
        if extent <= 0 or not np.isfinite(extent):
            raise ValueError(f"DensityController: scene extent must be positive, got {extent}")
        self.cfg, self.extent = cfg, float(extent)
        self._reset_stats(count)

    def _reset_stats(self, n: int):
        self.grad_accum = np.zeros(n, np.float64)        # [N] Σ ‖∂L/∂μ_ndc‖
        self.denom = np.zeros(n, np.float64)             # [N] views in which the surfel was seen

    def accumulate(self, grad_means: np.ndarray, means: np.ndarray, cam_pos: np.ndarray,
                   tan_half_fov: float) -> None:
        """Add one view's NDC-space gradient norms (surfels with zero gradient are unseen)."""
        v = means - cam_pos[None]                         # [N, 3]
        z = np.linalg.norm(v, axis=1)
        d = v / np.maximum(z, 1e-12)[:, None]
        g_perp = grad_means - (grad_means * d).sum(1, keepdims=True) * d
        g = np.linalg.norm(g_perp, axis=1) * z * tan_half_fov
        g = np.where(np.isfinite(g), g, 0.0)
        seen = np.any(grad_means != 0, axis=1)
        self.grad_accum += g * seen
        self.denom += seen

    def due(self, it: int, progress: float = 0.0) -> bool:
        """Densify at iteration ``it``? ``progress``: the run's fraction done (iterations or
        time budget, whichever is further), compared with ``until``."""
        c = self.cfg
        return c.start <= it <= c.stop and progress <= c.until and it % c.interval == 0

    def reset_due(self, it: int, progress: float = 0.0) -> bool:
        c = self.cfg
        return (it > 0 and it % c.opacity_reset_interval == 0 and it <= c.stop
                and progress <= c.until)

    # ------------------------------------------------------------------ edits
    def densify_and_prune(self, params: SurfelParams, opt=None, keys: dict | None = None,
                          rng: np.random.Generator | None = None) -> tuple[SurfelParams, dict]:
        """Clone small / split large high-gradient surfels, prune transparent/huge ones.

        ``opt``/``keys``: a drjit.opt optimiser and {field: optimiser key}; its
        parameters and moments are rewritten to the new surfel set.
        Returns (new params, counts {cloned, split, pruned, total}).
        """
        rng = rng or np.random.default_rng(0)
        c = self.cfg
        p = params.to_numpy()
        n = len(p["opacity_logit"])
        grad = np.where(self.denom > 0, self.grad_accum / np.maximum(self.denom, 1), 0.0)
        scale = np.exp(np.clip(p["log_scales"], -20, 12)).max(1)
        hot = grad >= c.grad_threshold
        # Early in a short schedule nearly every surfel exceeds the 3DGS threshold; growing
        # them all at once doubles the count per step and wrecks the fit, so only
        # the largest gradients up to max_fraction (and the max_surfels budget) are taken.
        budget = min(max(0, c.max_surfels - n) // max(c.split_children, 1), int(c.max_fraction * n))
        if hot.sum() > budget:
            order = np.argsort(-grad)
            hot = np.zeros(n, bool)
            hot[order[:budget]] = True
            hot &= grad >= c.grad_threshold
        clone = hot & (scale <= c.percent_dense * self.extent)
        split = hot & ~clone
        src = np.concatenate([np.arange(n), np.nonzero(clone)[0],
                              np.repeat(np.nonzero(split)[0], c.split_children)])
        new = {k: v[src].copy() for k, v in p.items()}
        m = n + int(clone.sum())
        if split.any():                                # children sampled in the tangent plane
            ch = src[m:]
            R = quat_to_matrix(p["quats"][ch])           # [S, 3, 3]
            s = np.exp(p["log_scales"][ch])              # [S, 2]
            off = rng.normal(size=(len(ch), 2)) * s
            new["means"][m:] = p["means"][ch] + np.einsum("sij,sj->si", R[:, :, :2], off)
            new["log_scales"][m:] = p["log_scales"][ch] - np.log(0.8 * c.split_children)
        if c.clone_opacity_split and clone.any():
            # a clone sits on its source: the pair covers 1 − (1 − α')², so α' = 1 − √(1 − α)
            # keeps the image unchanged (Rota Bulò et al. 2024, "Revising densification")
            both = np.r_[np.nonzero(clone)[0], n + np.arange(int(clone.sum()))]
            a = 1 / (1 + np.exp(-np.clip(new["opacity_logit"][both], -30, 30)))
            a2 = np.clip(1 - np.sqrt(np.clip(1 - a, 0, 1)), 1e-6, 1 - 1e-6)
            new["opacity_logit"][both] = np.log(a2 / (1 - a2))
        opacity = 1 / (1 + np.exp(-np.clip(new["opacity_logit"], -30, 30)))
        big = np.exp(np.clip(new["log_scales"], -20, 12)).max(1) > c.max_scale * self.extent
        finite = np.all([np.all(np.isfinite(v.reshape(len(src), -1)), 1) for v in new.values()], 0)
        drop = np.zeros(len(src), bool)
        drop[:n] |= split                              # split parents are replaced by children
        drop |= (opacity < c.min_opacity) | big | ~finite
        keep = ~drop
        if not keep.any():
            raise RuntimeError("densify_and_prune: every surfel would be pruned; check learning "
                               "rates / thresholds (min_opacity, max_scale)")
        out = SurfelParams.from_numpy(**{k: v[keep] for k, v in new.items()})
        if opt is not None:
            _remap_optimizer(opt, keys, src[keep], np.arange(len(src))[keep] < n, out, n)
        self._reset_stats(out.count)
        return out, {"cloned": int(clone.sum()), "split": int(split.sum()),
                     "pruned": int((~keep).sum() - split.sum()), "total": out.count}

    def reset_opacity(self, params: SurfelParams, opt=None, keys: dict | None = None) -> SurfelParams:
        """opacity ← min(opacity, reset value); zero the opacity moments (3DGS)."""
        p = params.to_numpy()
        cap = np.log(self.cfg.opacity_reset_value / (1 - self.cfg.opacity_reset_value))
        p["opacity_logit"] = np.minimum(p["opacity_logit"], cap)
        out = SurfelParams.from_numpy(**p)
        if opt is not None and "opacity_logit" in (keys or {}):
            key = keys["opacity_logit"]
            opt[key] = out.opacity_logit
            opt.reset(key)
        return out


def _remap_optimizer(opt, keys: dict, src: np.ndarray, old: np.ndarray, new: SurfelParams, n_old: int):
    """Rewrite optimiser values to ``new`` and its Adam moments by ``src`` (zero where not ``old``)."""
    for field, key in keys.items():
        if key not in opt.state:
            continue
        value, promoted, lr, extra = opt.state[key]
        t, m, v, vmax = extra
        like = getattr(new, field)
        opt[key] = like                      # new shape -> resets the state; restore below
        mm = field_to_numpy(field, m, n_old)[src]
        vv = field_to_numpy(field, v, n_old)[src]
        mm[~old] = 0                         # new surfels: no momentum, but their source's
        # second moment: Adam's step count is shared by all surfels, so with v = 0 and no
        # bias correction a new surfel's step is lr·(1 − 0.9^k)/√(1 − 0.999^k): 6.5× lr after
        # 10 steps, 3× after 100: large enough to throw the new surfels off the surface
        value2, promoted2, lr2, _ = opt.state[key]
        opt.state[key] = (value2, promoted2, lr, (t, field_from_numpy(field, mm, like),
                                                  field_from_numpy(field, vv, like), None))


def extent_from_cameras(cam_positions: np.ndarray) -> float:
    """3DGS scene extent: 1.1 × the largest camera distance from the cameras' centroid."""
    c = cam_positions.mean(0)
    return float(1.1 * np.linalg.norm(cam_positions - c, axis=1).max())
