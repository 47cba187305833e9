"""Density-control strategy of step 1, in the manner of gsplat's ``strategy/default.py``.

One object owns the whole policy: what is accumulated after each backward pass (the
view-space gradient of every surfel's position), when surfels are cloned, split and
pruned, when opacities are reset, and the budget of surfels a run may grow to. The
trainer calls :meth:`DefaultStrategy.step_post_backward` once per iteration and installs
what it returns; the mechanics (NumPy edits that keep the Adam moments aligned) are
:class:`comgs_dr.train.density.DensityController`'s.

Why our own and not gsplat's: gsplat's strategies act on PyTorch tensors and optimisers;
ours edit Dr.Jit arrays and ``mi.ad.Adam`` state, and measure the view-space gradient
from a ray tracer's world-space gradient (``density`` module docstring).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from comgs_dr.surfels.params import SurfelParams
from comgs_dr.train.density import DensityConfig, DensityController


@dataclasses.dataclass
class StepInfo:
    """What the strategy needs of one training step (host arrays).

    ``grad_means`` [N, 3]: ∂L/∂μ of this step (zero for surfels the view did not see);
    ``means`` [N, 3]; ``camera`` [3]: the view's centre; ``tan_half_fov``: tan(fov_x / 2).
    """
    grad_means: np.ndarray
    means: np.ndarray
    camera: np.ndarray
    tan_half_fov: float


@dataclasses.dataclass
class StepEdits:
    """What :meth:`DefaultStrategy.step_post_backward` changed: a new surfel set to install
    (``params``; its optimiser state already remapped), new opacity logits after a reset
    (``opacity_logit``), and the counts to log."""
    params: SurfelParams | None = None
    opacity_logit: object = None
    stats: dict = dataclasses.field(default_factory=dict)


class DefaultStrategy:
    """Clone / split by accumulated view-space gradient, prune, opacity reset (3DGS/2DGS).

    Every ``interval`` iterations between ``start`` and ``stop`` (and before the ``until``
    fraction of the run), surfels whose mean view-space gradient exceeds
    ``grad_threshold`` are cloned (small: σ ≤ ``percent_dense`` · extent) or split (large),
    at most ``max_fraction`` of the surfels per step and never beyond ``max_surfels`` (the
    budget that keeps a 2-core run's iteration time bounded); surfels below
    ``min_opacity`` or above ``max_scale`` · extent are pruned. Opacities are reset every
    ``opacity_reset_interval`` iterations. ``DensityConfig`` documents each field.
    """

    def __init__(self, cfg: DensityConfig, count: int, extent: float):
        self.cfg = cfg
        self.controller = DensityController(cfg, count, extent)

    @property
    def grows(self) -> bool:
        """Whether this strategy ever adds surfels (False: prune only)."""
        return self.cfg.max_fraction > 0 and self.cfg.max_surfels > 0

    def reset_state(self, count: int) -> None:
        """Forget the accumulated gradients (after a restore or an outside edit)."""
        self.controller._reset_stats(count)

    def step_post_backward(self, info: StepInfo) -> None:
        """After the backward pass, before the optimiser step: accumulate this step's
        view-space gradients."""
        self.controller.accumulate(info.grad_means, info.means, info.camera, info.tan_half_fov)

    def step_post_update(self, params: SurfelParams, opt, keys: dict, step: int,
                         progress: float, rng: np.random.Generator) -> StepEdits:
        """After the optimiser step: densify/prune and reset the opacities when due.

        ``step``: the iteration just completed (1-based); ``progress``: the fraction of the
        run done (iterations or time budget); ``keys``: {field: optimiser key}.
        """
        ctl = self.controller
        edits = StepEdits()
        if ctl.due(step, progress):
            params, counts = ctl.densify_and_prune(params, opt, keys, rng)
            edits.params = params
            edits.stats.update({f"densify_{k}": v for k, v in counts.items()})
        if ctl.reset_due(step, progress):
            new = ctl.reset_opacity(params, opt, {"opacity_logit": keys["opacity_logit"]})
            edits.opacity_logit = new.opacity_logit
            edits.stats["opacity_reset"] = 1
        return edits


def tan_half(fov_x_deg: float) -> float:
    """tan(fov_x / 2) of a horizontal field of view in degrees."""
    return math.tan(math.radians(fov_x_deg) / 2)
