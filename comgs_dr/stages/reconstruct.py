"""Reconstruction step 1: surfel radiance + geometry from multi-view images.

Loss (paper eq. loss_render, d2n, mask): L = L1 + 0.2(1 − SSIM) + λ_d2n (1 − N·N_d)
+ λ_mask BCE(W, K). Adam (``drjit.opt``) with per-parameter learning rates (3DGS/2DGS
values, positions scaled by the scene extent and decayed exponentially), 2DGS
adaptive density control, atomic checkpoints with resume, a JSON log of loss / PSNR /
surfel count against wall-clock time, a progress bar with ETA and a PSNR plot.

One training view per iteration (full image): SSIM needs image structure, and on the
CPU the per-iteration cost is dominated by fixed overheads (BVH update, kernel
launches) that a smaller random ray batch would not remove.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.cameras import camera_rays
from comgs_dr.core.hostarray import to_jit
from comgs_dr.eval.metrics import psnr
from comgs_dr.surfels import kernel as Kn
from comgs_dr.surfels import save_ply
from comgs_dr.surfels.params import (
    SurfelParams,
    field_from_numpy,
    field_names,
    field_to_numpy,
)
from comgs_dr.surfels.scene import gbuffer_scene
from comgs_dr.train import background as bgenv
from comgs_dr.train import checkpoint as ck
from comgs_dr.train import exposure as ex
from comgs_dr.train.init import initial_surfels  # noqa: F401 (part of this stage's API)
from comgs_dr.train import losses as L
from comgs_dr.train.density import DensityConfig
from comgs_dr.train.strategy import DefaultStrategy, StepInfo, tan_half
from comgs_dr.train.loop import BestState, TrainerBase, finish, run_loop, zero_nonfinite_grads
from comgs_dr.train.schedule import log_lerp

log = logging.getLogger(__name__)

CKPT_FORMAT = "comgs_dr.checkpoint/1"
NEAR_CLIP_FRAC, FAR_CLIP_FRAC = 1e-4, 1e4     # sensor clip planes × the scene extent
PARAM_KEYS = {f: f"surfels.{f}" for f in field_names() if f not in ("albedo", "roughness", "metallic")}


@dataclasses.dataclass
class RadianceConfig:
    """Step-1 settings; ``RadianceConfig.from_preset(name, **overrides)`` for a named preset.

    Presets (``PRESETS``): ``object`` starts from the visual hull's surface along the training
    pixels' rays (:func:`comgs_dr.train.init.hull_ray_points`: unlike a volume-carved shell,
    its points reach structures thinner than a pixel), adds the mask loss, caps σ at 1 % of the
    extent and uses a lower scale learning rate; ``scene`` starts from the dataset's points
    (COLMAP, or ``points3d.ply`` beside NeRF-style JSON), else random points in the common view
    frustum, has no mask loss and caps σ at 2 %.

    Defaults that differ from 2DGS, and why:

    * ``lambda_d2n`` 0.2 from iteration 300 (paper 0.05 from 7k of 30k): in runs of a few
      thousand iterations the weaker, later depth–normal prior lets the surfaces drift and the
      fit collapse after its peak.
    * ``init_opacity`` 0.5 (3DGS 0.1): the hull and point inits already lie on the surface;
      ``init_normals`` off: normals from the initial points help the first few hundred
      iterations and hurt later.
    * colour learning rates 2× 3DGS; scale and rotation rates as 3DGS (larger ones grow hazy
      surfels).
    * prune-only density control (``densify=None``); the strategy
      (:class:`comgs_dr.train.strategy.DefaultStrategy`) clones/splits with ``densify``
      (DensityConfig fields, {} for its 2DGS defaults). With every surfel on a ray composited,
      clone/split adds surfels without improving the fit, so it is off by default.
    * ``init_sweep_points`` (scene preset, None: 4000 when the points are sparse): SfM
      leaves low-texture surfaces of real photos (walls, bedding, furniture) nearly empty;
      surfels grown from its sparse points alone cover ~40 % of a phone photo and the rest
      falls to the blurry far-field background (20-photo phone capture: 17.9 dB on the
      training views, 17.8 dB held out). Plane-swept points (the ``nearfar`` init, with
      each view's near/far from the SfM points it sees) fill them: 23 dB held out
      (docs/real_capture.md). 2DGS clone/split does not (its opacity reset costs more than
      its few splits add: 12 dB).
    * ``exposure`` off by default: a per-view affine colour map for photos whose exposure
      and white balance vary (train.exposure).
    * ``max_scale_frac`` (largest σ / extent; None: the preset's): without a cap a few object
      surfels grow to a large fraction of the object and haze the fit, and a scene grows hazy
      floaters.
    """
    preset: str = "object"
    iterations: int = 3000
    max_hits: int = 128                   # hit-buffer slots per ray and pass
    max_passes: int = 16                  # passes of max_hits: every surfel on a ray is
                                          # composited (1: the first max_hits only)
    sh_degree: int = 2
    sh_increase_every: int = 250          # one SH band more every this many its (3DGS: 1000)
    init_points: int = 20_000
    init: str = "auto"                    # auto | hull | points | nearfar | random | <path.ply>
    init_normals: bool = False            # surfels tangent to the initial points (PCA)
    # init "points": the dataset's points + this many plane-swept ones (train.init.
    # sweep_fill_points, per-view near/far from the SfM points each view sees); None: the
    # scene preset adds train.init.SWEEP_FILL (4000, at most up to init_points) to points
    # sparser than train.init.SWEEP_SPARSE_PER_PIXEL (0.005: real photos' SfM), object 0
    init_sweep_points: int | None = None
    init_opacity: float = 0.5             # hull/points init
    lambda_ssim: float = 0.2
    lambda_d2n: float = 0.2
    lambda_mask: float = 0.05             # object preset only
    random_background: bool = True        # datasets with alpha: a random grey behind each step
    background: str = "auto"              # auto | grey | env: a learned sky / far field
                                          # (train.background); auto: resolve_background
    env_resolution: int = 64              # octahedral texels per side of the env background
    lr_env: float = 0.01
    # None: constant; else lr_env decays exponentially to it (a low final rate cleans a
    # smooth sky but under-fits a detailed one)
    lr_env_final: float | None = None
    lambda_binary: float = 0.05           # coverage entropy, with the env background only
    init_far_field: bool = True           # env background + near/far init: pixels as
                                          # consistent at infinity are left to the background
    lambda_env_tv: float = 0.01           # total variation of the env background
    d2n_from: int = 300
    lr_means: float = 1.6e-4              # × scene extent, decays to lr_means_final
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 5e-3
    lr_sh_rest: float = 5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    densify: dict | None = None           # DensityConfig fields; None: prune only
    max_scale_frac: float | None = None   # largest σ / scene extent; None: the preset's
    eval_every: int = 250
    eval_views: int = 8
    log_every: int = 25
    checkpoint_every: int = 500
    checkpoint_every_s: float | None = 300.0   # also by wall time; SIGINT/SIGTERM write one too
    seed: int = 0
    time_limit_s: float | None = None     # stop early (after a checkpoint) when exceeded
    restore_best: bool = True             # end on the best evaluated state if the final one
                                          # fell > 0.5 dB below it (reported as ``diverged``)
    # per-view exposure / white balance (train.exposure): a learnt affine colour map of each
    # training view's render, re-centred to the views' mean; held-out views are rendered
    # without one (psnr_test) and also colour-corrected (psnr_test_exposure)
    exposure: bool = False
    lr_exposure: float = 0.01             # decays exponentially to lr_exposure_final
    lr_exposure_final: float = 1e-3

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"RadianceConfig.preset must be 'object' or 'scene', got {self.preset!r}")
        if self.iterations < 1:
            raise ValueError("RadianceConfig.iterations must be ≥ 1")
        if self.sh_degree not in (0, 1, 2, 3):
            raise ValueError("RadianceConfig.sh_degree must be 0..3")
        if self.background not in ("auto", "grey", "env"):
            raise ValueError(f"RadianceConfig.background must be 'auto', 'grey' or 'env', got "
                             f"{self.background!r}")
        if self.env_resolution < 4:
            raise ValueError("RadianceConfig.env_resolution must be >= 4")
        if not (self.lr_env > 0 and (self.lr_env_final is None or self.lr_env_final > 0)):
            raise ValueError(f"RadianceConfig.lr_env and lr_env_final must be > 0, got "
                             f"{self.lr_env}, {self.lr_env_final}")
        if self.densify is None:
            self.densify = dict(max_fraction=0.0, opacity_reset_interval=10 ** 9)
        if self.max_scale_frac is None:
            self.max_scale_frac = PRESETS[self.preset]["max_scale_frac"]
        if not 0 < self.max_scale_frac <= 1.0:
            raise ValueError("RadianceConfig.max_scale_frac must be in (0, 1]")
        if not (self.lr_exposure > 0 and self.lr_exposure_final > 0):
            raise ValueError(f"RadianceConfig.lr_exposure and lr_exposure_final must be > 0, got "
                             f"{self.lr_exposure}, {self.lr_exposure_final}")
        if self.init_sweep_points is not None and self.init_sweep_points < 0:
            raise ValueError("RadianceConfig.init_sweep_points must be >= 0 or None")

    @classmethod
    def from_preset(cls, name: str, **overrides) -> "RadianceConfig":
        if name not in PRESETS:
            raise ValueError(f"unknown step-1 preset {name!r}: {', '.join(PRESETS)}")
        return cls(**{**PRESETS[name], "preset": name, **overrides})

    def loss(self) -> L.Step1Loss:
        """The step-1 loss with this config's weights (no mask term for scenes)."""
        return L.Step1Loss(lambda_d2n=self.lambda_d2n, lambda_ssim=self.lambda_ssim,
                           lambda_mask=self.lambda_mask if self.preset == "object" else 0.0,
                           lambda_binary=self.lambda_binary if self.background == "env" else 0.0,
                           d2n_from_iteration=self.d2n_from)


# object: max_scale_frac 0.01 of the extent is a compromise: an object with sub-pixel detail
# fits better with a tighter cap, a smooth one loses with it, and neither a cap relative to
# the object's radius nor one relative to the initial surfel spacing suits both.
# object: lr_scales 1e-3 (not 5e-3): at 5e-3 the σ of some surfels grows to the cap and the
# test PSNR falls; at 1e-3 hidden surfels fade instead (and are pruned).
PRESETS = {"object": {"max_scale_frac": 0.01, "lr_scales": 1e-3}, "scene": {"max_scale_frac": 0.02}}


def scaled_density_schedule(iterations: int) -> dict:
    """``RadianceConfig.densify`` for 2DGS density control on a schedule scaled to the run
    (2DGS: densify until 15k of 30k its, reset every 3k): densify until half of the run,
    reset the opacities at its quarter and half."""
    return dict(stop=max(1, iterations // 2), opacity_reset_interval=max(1, iterations // 4))


def _with_sh_degree(p: SurfelParams, degree: int) -> SurfelParams:
    d = p.to_numpy()
    k = (degree + 1) ** 2
    sh = np.zeros((len(d["sh"]), k, 3), np.float32)
    m = min(k, d["sh"].shape[1])
    sh[:, :m] = d["sh"][:, :m]
    d["sh"] = sh
    return SurfelParams.from_numpy(**d)


class Trainer(TrainerBase):
    """Step 1's :class:`~comgs_dr.train.loop.TrainerBase`: owns the scene, the optimiser and
    the density controller of one run."""

    def __init__(self, data, run_dir, cfg: RadianceConfig, progress: bool = True):
        cfg, self.background_reason = resolve_background(cfg, data)
        self.data, self.cfg, self.progress = data, cfg, progress
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.rng = np.random.default_rng(cfg.seed)
        self.extent = max(float(data.bounds[1]), 1e-6)
        resumed = ck.load_checkpoint(self.run_dir / ck.CKPT_NAME, CKPT_FORMAT)
        self.best = BestState()
        if resumed is not None:
            arrays, moments, state = resumed
            try:
                params = SurfelParams.from_numpy(**{k: arrays[k] for k in field_names()})
                self.iteration, self.log = int(state["iteration"]), list(state["log"])
                self.elapsed, self.init_desc = float(state["elapsed"]), state["init"]
                self.best.from_checkpoint(arrays, state.get("best"))
                if "rng_state" in state:        # the stream continues exactly where it was
                    self.rng.bit_generator.state = state["rng_state"]
                else:                           # checkpoints of older versions
                    self.rng = np.random.default_rng(state["rng_seed"])
            except (KeyError, ValueError, TypeError) as e:
                raise ValueError(f"checkpoint {self.run_dir / ck.CKPT_NAME} does not hold a "
                                 f"usable step-1 state ({type(e).__name__}: {e}); delete it "
                                 "to start over") from e
        else:
            params, self.init_desc = initial_surfels(data, cfg, self.rng)
            params = _with_sh_degree(params, 0)
            moments, self.iteration, self.log, self.elapsed = None, 0, [], 0.0
        self.views = data.train
        # clip planes relative to the scene (Mitsuba's defaults, 0.01 and 1e4, are absolute)
        clip = dict(near_clip=NEAR_CLIP_FRAC * self.extent, far_clip=FAR_CLIP_FRAC * self.extent)
        sensors = [v.camera.sensor_dict(**clip) for v in self.views + data.test]
        targets = "color,weight,depth_unbiased,normal" if cfg.lambda_d2n > 0 else "color,weight"
        bg = 1.0 if data.white_background else 0.0
        self.background = bg
        self.env = cfg.background == "env"
        # views' masks are the images' alpha unless a masks folder was given (COLMAP feature
        # masks, where 0 may mean "ignore this sky"): only alpha says a pixel shows nothing
        self.alpha_masks = not (getattr(data, "meta", None) or {}).get("masks")
        if self.env and self.alpha_masks:
            clear = transparent_fraction(self.views)
            if clear > 0.01:
                log.warning("reconstruct: --background env on images with transparent pixels "
                            "(%.1f%% of the training pixels have alpha < 0.5): they show no "
                            "sky, so the background learnt there is not the sky; it is recorded "
                            "as unobserved and estimate-light leaves it to the completion. "
                            "Learning a sky needs captures that show it (opaque photos)",
                            100 * clear)
        extra = dict(environment=bgenv.initial_emitter(cfg.env_resolution, self.views),
                     env_background=True) if self.env else {}
        self.scene = gbuffer_scene({"surfels": params}, sensors, max_hits=cfg.max_hits,
                                   max_passes=cfg.max_passes,
                                   targets=targets, background=bg, **extra)
        self.integ = self.scene.integrator()
        self.mp = mi.traverse(self.scene)
        # update() walks every kept key: leave the sensors out
        self.mp.keep(r"surfels\..*|environment\.data")
        if resumed is not None and self.env and "env" in arrays:   # (its Adam restarts)
            self.mp[bgenv.KEY] = to_jit(mi.TensorXf, arrays["env"])
        self.shape = self.scene.shapes()[0]
        self.opt = mi.ad.Adam(lr=1.0)
        self._register(params)
        # the background has its own Adam, which moves only texels with a gradient: most
        # views do not see most of the sky, and momentum-only steps made it drift into noise
        self.env_opt = mi.ad.Adam(lr=cfg.lr_env, mask_updates=True) if self.env else None
        if self.env:
            self.env_opt[bgenv.KEY] = self.mp[bgenv.KEY]
            self.mp.update(self.env_opt)
        if moments is not None:
            try:
                ck.restore_moments(self.opt, PARAM_KEYS, moments, field_from_numpy)
            except (KeyError, ValueError, TypeError, RuntimeError) as e:
                raise ValueError(f"checkpoint {self.run_dir / ck.CKPT_NAME}: its Adam state does "
                                 f"not fit its surfels ({e}); delete it to start over") from e
        self.strategy = DefaultStrategy(DensityConfig(**cfg.densify), params.count, self.extent)
        self.targets = [to_jit(mi.TensorXf, v.image) for v in self.views]
        self.masks = [None if v.mask is None else to_jit(mi.TensorXf, v.mask[..., None])
                      for v in self.views]
        self._rays = {}
        self.loss_fn = cfg.loss()
        self.exposure = ex.ViewExposure(len(self.views), cfg.lr_exposure) if cfg.exposure else None
        if self.exposure is not None and not self.env and cfg.random_background \
                and all(m is not None for m in self.masks):
            log.warning("reconstruct: exposure=True with a random background behind views with "
                        "alpha: the correction applies to the whole composite, whose random "
                        "grey the photo did not take; it is meant for opaque photos "
                        "(set random_background=False or exposure=False)")
        if self.exposure is not None and resumed is not None and "exposure" in arrays:
            self.exposure.load(arrays["exposure"])

    # ------------------------------------------------------------- params
    def _install(self, params: SurfelParams):
        """Put every field of ``params`` (any count) into the scene; rebuilds proxies + BVH."""
        for f in field_names():
            self.mp[f"surfels.{f}"] = getattr(params, f)
        self.mp.update()

    def _register(self, params: SurfelParams):
        self._install(params)
        for key in PARAM_KEYS.values():
            self.opt[key] = self.mp[key]
        self._set_learning_rates()
        self.mp.update(self.opt)
        dr.eval()

    def _set_learning_rates(self):
        c = self.cfg
        k = self.shape.params.sh_coeffs
        n = self.shape.params.count
        sh_lr = np.full((n, k, 3), c.lr_sh_rest, np.float32)
        sh_lr[:, 0] = c.lr_sh_dc
        self.opt.set_learning_rate({
            "surfels.means": self._lr_means(), "surfels.sh": to_jit(mi.Float, sh_lr.ravel()),
            "surfels.opacity_logit": c.lr_opacity, "surfels.log_scales": c.lr_scales,
            "surfels.quats": c.lr_quats})

    def run_fraction(self) -> float:
        """Fraction of the run done: iterations, or the time budget when that ends it first.
        The position learning rate decays and densification stops on this clock, so a run
        with ``time_limit_s`` uses its whole budget whatever the iteration speed."""
        c = self.cfg
        p = self.iteration / max(c.iterations, 1)
        if c.time_limit_s:
            p = max(p, self.elapsed / c.time_limit_s)
        return min(p, 1.0)

    def _lr_means(self) -> float:
        c = self.cfg
        t = self.run_fraction()
        return float(self.extent * log_lerp(c.lr_means, c.lr_means_final, t))

    def _lr_exposure(self) -> float:
        c = self.cfg
        return float(log_lerp(c.lr_exposure, c.lr_exposure_final, self.run_fraction()))

    def _lr_env(self) -> float:
        c, t = self.cfg, self.run_fraction()
        if c.lr_env_final is None:
            return float(c.lr_env)
        return float(log_lerp(c.lr_env, c.lr_env_final, t))

    def params(self) -> SurfelParams:
        return self.shape.params

    # ---------------------------------------------------------------- loss
    def _view_rays(self, i: int):
        if i not in self._rays:
            sensor = self.scene.sensors()[i]
            cam = (self.views + self.data.test)[i].camera
            self._rays[i] = camera_rays(sensor, cam.width, cam.height)
        return self._rays[i]

    def loss(self, i: int, img, background: float | None = None):
        """(total, logged parts, buffers) of :class:`Step1Loss` for training view ``i``
        rendered over the grey level ``background`` (None: the dataset's)."""
        parts = self.integ.split(img)
        if self.exposure is not None:           # this view's exposure / white balance
            parts["color"] = self.exposure.apply(parts["color"], i)
        lf = self.loss_fn
        rays = self._view_rays(i) if lf.d2n_active(self.iteration) else None
        total, logged = lf(parts, self._target(i, background), self.masks[i], rays, self.iteration)
        if self.env and self.cfg.lambda_env_tv > 0:
            tv = bgenv.total_variation(self.env_opt[bgenv.KEY])
            total = total + self.cfg.lambda_env_tv * tv
            logged["env_tv"] = float(tv[0])
        return total, logged, parts

    def _target(self, i: int, background: float | None):
        """The training image of view ``i`` re-composited over ``background``: the stored
        image is over the dataset's background b₀, so I_b = I + (1 − α)(b − b₀)."""
        if background is None or background == self.background or self.masks[i] is None:
            return self.targets[i]
        shift = dr.opaque(mi.TensorXf, background - self.background, (1, 1, 1))   # no recompile
        return self.targets[i] + (1.0 - self.masks[i]) * shift

    def _step_background(self) -> float | None:
        """A uniform random grey behind this step's render and target (views with alpha).

        Over a fixed black (or white) background, lowering a surfel's opacity darkens (or
        brightens) the pixel, so the photometric loss can fit shading and view-dependent
        colour with holes in the silhouette. Behind a random grey a hole is wrong on
        average, as NeRF trainers do for RGBA data.
        """
        if self.env or not self.cfg.random_background or any(m is None for m in self.masks):
            return None
        return float(self.rng.uniform(0.0, 1.0))

    # ---------------------------------------------------------------- step
    def step(self) -> dict:
        c = self.cfg
        it = self.iteration
        if c.sh_increase_every and it > 0 and it % c.sh_increase_every == 0 \
                and self.params().sh_degree < c.sh_degree:
            self._resize(_with_sh_degree(self.params(), self.params().sh_degree + 1), remap=None)
        i = int(self.rng.integers(len(self.views)))
        bg = self._step_background()
        if self.exposure is not None:
            self.exposure.zero_grad()
        self.integ.background = self.background if bg is None else bg   # render + adjoint
        try:
            img = mi.render(self.scene, self.mp, sensor=i, seed=it)
            total, parts, bufs = self.loss(i, img, bg)
            dr.backward(total)
        finally:
            self.integ.background = self.background
        nan_grads = self._guard_gradients()
        hit_stats = self._hit_stats()
        self.strategy.step_post_backward(StepInfo(
            grad_means=np.asarray(dr.grad(self.opt["surfels.means"])).T,
            means=np.asarray(self.opt["surfels.means"]).T,
            camera=np.asarray(self.views[i].camera.to_world)[:3, 3],
            tan_half_fov=tan_half(self.views[i].camera.fov_x_deg)))
        # Adam sees the gradient w.r.t. positions in units of the scene extent: its ε would
        # otherwise damp the steps of large scenes (∂L/∂μ ∝ 1/scale) and the fit would
        # depend on the unit of length; the learning rate carries the extent back.
        key = "surfels.means"
        dr.set_grad(self.opt[key], dr.grad(self.opt[key]) * self.extent)
        self.opt.set_learning_rate({key: self._lr_means()})
        self.opt.step()
        self._clamp()
        if self.exposure is not None:
            nan_grads += self.exposure.step(self._lr_exposure())
        if self.env:
            self.env_opt.set_learning_rate({bgenv.KEY: self._lr_env()})
            self.env_opt.step()
            bgenv.clamp(self.env_opt)
            self.mp[bgenv.KEY] = self.env_opt[bgenv.KEY]
        self.mp.update(self.opt)
        self.iteration += 1
        stats = dict(parts)
        stats["loss"] = stats.pop("total")
        c_img = np.asarray(bufs["color"])
        stats["psnr_train"] = psnr(c_img, np.asarray(self._target(i, bg)))
        stats["nan_grads"] = nan_grads
        stats.update(hit_stats)
        if self.exposure is not None:
            stats.update(self.exposure.stats())
        edits = self.strategy.step_post_update(self.params(), self.opt, PARAM_KEYS,
                                               self.iteration, self.run_fraction(), self.rng)
        if edits.params is not None:
            self._resize(edits.params, remap="done")
        if edits.opacity_logit is not None:
            self.mp["surfels.opacity_logit"] = edits.opacity_logit
            self.mp.update(self.opt)
        stats.update(edits.stats)
        return stats

    def _hit_stats(self) -> dict:
        """Instruments of this step's render (from the integrator's cached primal state):
        ``open_frac``, the share of pixels whose transmittance after the last composited
        hit is still above 1e-3 while the hit buffer is full (compositing stopped early:
        what lies behind got no gradient and the background showed through), and
        ``hits_mean``, the mean number of composited hits per pixel."""
        cache = getattr(self.integ, "_primal_cache", None)
        if cache is None:
            return {}
        hits, _, T, _ = cache[1]
        count, T = np.asarray(hits.count), np.asarray(T)
        return {"open_frac": float(np.mean((count >= hits.K) & (T > 1e-3))),
                "hits_mean": float(count.mean()), "hits_max": int(count.max(initial=0)),
                "stopped_early": float(self.integ.stopped_early)}

    def diagnostics(self) -> dict:
        """Surfel statistics logged with every record: the share of surfels whose largest σ
        sits at the cap (``sigma_cap_frac``), the opacity histogram (shares below 0.05,
        below 0.5, above 0.9) and the mean Adam second moment of the opacity logits."""
        p = self.params()
        ls = np.asarray(dr.detach(p.log_scales)).reshape(2, -1).max(0)
        cap = math.log(self.cfg.max_scale_frac * self.extent)
        op = 1.0 / (1.0 + np.exp(-np.asarray(dr.detach(p.opacity_logit))))
        out = {"sigma_cap_frac": float(np.mean(ls >= cap - 1e-3)),
               "opacity_lt_005": float(np.mean(op < 0.05)), "opacity_lt_05": float(np.mean(op < 0.5)),
               "opacity_gt_09": float(np.mean(op > 0.9))}
        st = self.opt.state.get("surfels.opacity_logit")    # (value, promoted, lr, (t, m, v))
        if st is not None and st[3] is not None and st[3][2] is not None:
            out["adam_v_opacity"] = float(np.mean(np.asarray(st[3][2])))
        return out

    def _guard_gradients(self) -> int:
        """Replace non-finite gradients by 0 (counted, logged) so one bad ray cannot poison Adam."""
        bad = zero_nonfinite_grads(self.opt, PARAM_KEYS.values())
        return bad + (zero_nonfinite_grads(self.env_opt, [bgenv.KEY]) if self.env else 0)

    def _clamp(self):
        """Keep raw parameters in the ranges where activations are well behaved."""
        o = self.opt
        o["surfels.log_scales"] = dr.clip(o["surfels.log_scales"], Kn.LOG_SCALE_RANGE[0],
                                          math.log(self.cfg.max_scale_frac * self.extent))
        o["surfels.opacity_logit"] = dr.clip(o["surfels.opacity_logit"], -12.0, 12.0)

    def _resize(self, params: SurfelParams, remap):
        """Install a new surfel set (density control or SH growth) into scene + optimiser."""
        self._install(params)
        if remap is None:                       # SH growth: moments of sh restart at zero
            self.opt["surfels.sh"] = self.mp["surfels.sh"]
            self.opt.reset("surfels.sh")
        self._set_learning_rates()
        self.mp.update(self.opt)
        dr.eval()

    # ---------------------------------------------------------------- eval
    def _mean_psnr(self, views, offset: int, max_views: int | None,
                   fit: bool = False) -> tuple[float, int, float | None]:
        """Mean PSNR over (up to ``max_views`` of) ``views`` at sensors ``offset + j``:
        training views (offset 0) through their exposure correction; ``fit``: also the
        mean PSNR with a per-image affine colour fit (:func:`train.exposure.psnr_exposure_fit`)."""
        idx = np.unique(np.linspace(0, len(views) - 1, min(len(views), max_views or len(views)))
                        .round().astype(int))
        ps, pf = [], []
        for j in idx:
            img = mi.render(self.scene, sensor=offset + int(j))
            c = np.asarray(self.integ.split(img)["color"])
            if fit:
                pf.append(ex.psnr_exposure_fit(np.clip(c, 0, 1), views[j].image))
            if self.exposure is not None and offset == 0:
                c = self.exposure.apply_numpy(c, int(j))
            ps.append(psnr(c, views[j].image))
        return float(np.mean(ps)), len(ps), (float(np.mean(pf)) if fit else None)

    def evaluate(self, max_views: int | None = None) -> dict:
        """Test PSNR (held-out views as rendered, no exposure correction), ``psnr_test_exposure``
        (after a per-image affine colour fit, :func:`train.exposure.psnr_exposure_fit`), and
        ``psnr_select``: the PSNR of a fixed subset of training views (through their learnt
        exposure correction, when on), which alone chooses the best state (the test views
        never do)."""
        views = self.data.test or self.data.train
        off = len(self.views) if self.data.test else 0
        p_test, n, p_fit = self._mean_psnr(views, off, max_views, fit=True)
        p_sel, _, _ = self._mean_psnr(self.views, 0, max_views)
        out = {"psnr_test": p_test, "psnr_test_exposure": p_fit, "views": n, "psnr_select": p_sel}
        if self.loss_fn.d2n_active(self.iteration):
            out["d2n_grad_share"] = self.d2n_grad_share()
        return out

    def d2n_grad_share(self, view: int = 0) -> float:
        """‖∂(λ_d2n L_d2n)/∂θ‖ / ‖∂L/∂θ‖ over the surfels' rotations and positions on one
        training view: how much of the step the depth–normal prior drives (an instrument;
        the gradients are cleared afterwards)."""
        norms, keys = [], ("surfels.quats", "surfels.means")
        for key in keys:
            dr.set_grad(self.opt[key], 0)
        for part in ("d2n", "total"):
            img = mi.render(self.scene, self.mp, sensor=view, seed=0)
            bufs = self.integ.split(img)
            if part == "d2n":
                dirs, origins = self._view_rays(view)
                obj = self.loss_fn.lambda_d2n * L.d2n_loss(
                    bufs["normal"], bufs["depth_unbiased"], bufs["weight"], dirs, origins,
                    self.loss_fn.d2n_min_weight, self.loss_fn.detach_depth_normal)
            else:
                obj = self.loss(view, img)[0]
            dr.backward(obj)
            g = np.concatenate([np.asarray(dr.grad(self.opt[k])).ravel() for k in keys])
            norms.append(float(np.linalg.norm(np.nan_to_num(g))))
            for key in self.opt.keys():
                dr.set_grad(self.opt[key], 0)
            if self.exposure is not None:
                self.exposure.zero_grad()
        return norms[0] / max(norms[1], 1e-30)

    def snapshot(self) -> dict:
        """A host copy of the surfels (the Adam moments are not kept: a restored state
        ends the run)."""
        snap = self.params().to_numpy()
        if self.env:
            snap["env"] = np.array(self.mp[bgenv.KEY])
        if self.exposure is not None:
            snap["exposure"] = self.exposure.values()
        return snap

    def restore(self, state: dict) -> None:
        """Install a snapshot into the scene and the optimiser (moments restart at zero)."""
        state = dict(state)
        if self.env:
            self.mp[bgenv.KEY] = to_jit(mi.TensorXf, state.pop("env"))
        exposure = state.pop("exposure", None)
        if self.exposure is not None and exposure is not None:
            self.exposure.load(exposure)
        self._install(SurfelParams.from_numpy(**state))
        for key in PARAM_KEYS.values():
            self.opt[key] = self.mp[key]
            self.opt.reset(key)
        if self.env:
            self.env_opt[bgenv.KEY] = self.mp[bgenv.KEY]
            self.env_opt.reset(bgenv.KEY)
        self._set_learning_rates()
        self.mp.update(self.opt)
        self.strategy.reset_state(self.params().count)
        dr.eval()

    @property
    def checkpoint_path(self) -> Path:
        return self.run_dir / ck.CKPT_NAME

    def checkpoint(self):
        n = self.params().count
        best_arrays, best_record = self.best.to_checkpoint()
        ck.save_checkpoint(
            self.checkpoint_path, CKPT_FORMAT, {**self.snapshot(), **best_arrays}, self.opt,
            PARAM_KEYS, {"iteration": self.iteration, "log": self.log, "elapsed": self.elapsed,
                         "init": self.init_desc, "rng_state": self.rng.bit_generator.state,
                         "best": best_record, "config": dataclasses.asdict(self.cfg)},
            to_numpy=lambda f, v: field_to_numpy(f, v, n))

    def log_fields(self) -> dict:
        return {"surfels": self.params().count, **self.diagnostics()}

    def bar_fields(self) -> dict:
        """What the progress bar shows besides loss and PSNR (the log has the rest)."""
        return {"surfels": self.params().count}


def resolve_background(cfg: RadianceConfig, data) -> tuple[RadianceConfig, str]:
    """``background='auto'`` decided from the data: (config with 'grey' or 'env', reason).

    A capture whose photos are opaque sees past the reconstructed geometry wherever a view
    looks at the horizon, the sky or far walls; with a grey background those pixels render
    black or grey and the near surfels are bent to explain them. So: opaque training
    images of the scene preset learn the far field (``env``); images with transparent
    pixels (an object cut out by its alpha) show nothing behind and keep the grey level.
    """
    if cfg.background != "auto":
        return cfg, f"{cfg.background} (given)"
    clear = transparent_fraction(data.train)
    if cfg.preset == "scene" and clear <= 0.01:
        why = f"env: scene preset, opaque photos ({100 * clear:.1f}% transparent pixels)"
        return dataclasses.replace(cfg, background="env"), why
    why = (f"grey: {cfg.preset} preset, {100 * clear:.1f}% transparent training pixels")
    return dataclasses.replace(cfg, background="grey"), why


def transparent_fraction(views) -> float:
    """Share of the training pixels with alpha < ½ (views without a mask count as opaque)."""
    n = sum(v.image.shape[0] * v.image.shape[1] for v in views)
    clear = sum(int((v.mask < 0.5).sum()) for v in views if v.mask is not None)
    return clear / max(n, 1)


def train_radiance(data, run_dir, cfg: RadianceConfig, progress: bool = True) -> dict:
    """Run (or resume) step 1; writes point_cloud.ply, train_log.json, psnr_vs_time.png."""
    tr = Trainer(data, run_dir, cfg, progress)
    run_dir = Path(run_dir)
    stopped_early = run_loop(tr, cfg, "step 1", progress, log_dir=run_dir, best=tr.best,
                             jsonl_dir=run_dir, stage="reconstruct")
    final = tr.evaluate(cfg.eval_views)
    diverged = tr.best.settle(tr, final["psnr_select"], tr.iteration, "step 1",
                              restore=cfg.restore_best)
    final = tr.evaluate()
    save_ply(tr.params(), str(run_dir / "point_cloud.ply"))
    if tr.env:
        obs, clipped = bgenv.capture_maps(tr.scene, tr.integ, list(range(len(tr.views))),
                                          cfg.env_resolution, [v.image for v in tr.views],
                                          masks=[v.mask for v in tr.views]
                                          if tr.alpha_masks else None)
        bgenv.save(run_dir, np.array(tr.mp[bgenv.KEY]), obs, clipped)
    summary = {"iterations": tr.iteration, "train_seconds": tr.elapsed, "surfels": tr.params().count,
               "init": tr.init_desc, "background": tr.background_reason,
               "stopped_early": stopped_early, "diverged": diverged, **final,
               "config": dataclasses.asdict(cfg)}
    if tr.exposure is not None:     # per training view: (I + D | b), the learnt colour map
        ident = np.c_[np.eye(3), np.zeros(3)]
        summary["exposure"] = {v.name: np.round(ident + tr.exposure.matrix(j), 5).tolist()
                               for j, v in enumerate(tr.views)}
    return finish(tr, run_dir, summary, stage="reconstruct")
