"""Reconstruction step 1: surfel radiance + geometry from multi-view images.

Loss (paper eq. loss_render, d2n, mask): L = L1 + 0.2(1 − SSIM) + λ_d2n (1 − N·N_d)
+ λ_mask BCE(W, K). Adam (``drjit.opt``) with per-parameter learning rates (3DGS/2DGS
values, positions scaled by the scene extent and decayed exponentially), 2DGS
adaptive density control, atomic checkpoints with resume, a JSON log of loss / PSNR /
surfel count against wall-clock time, a progress bar with ETA and a PSNR plot.

One training view per iteration (full image): SSIM needs image structure, and on the
CPU the per-iteration cost is dominated by fixed overheads (BVH update, kernel
launches) that a smaller random ray batch would not remove (see benchmarks/recon_step1.py).
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from comgs_dr.core.cameras import camera_rays
from comgs_dr.eval.metrics import psnr
from comgs_dr.surfels import kernel as Kn
from comgs_dr.surfels import load_ply, save_ply
from comgs_dr.surfels.params import SurfelParams, field_names
from comgs_dr.surfels.scene import gbuffer_scene
from comgs_dr.train import checkpoint as ck
from comgs_dr.train import init as I
from comgs_dr.train import losses as L
from comgs_dr.train.density import DensityConfig, DensityController
from comgs_dr.train.loop import plot_psnr

PARAM_KEYS = {f: f"surfels.{f}" for f in field_names() if f not in ("albedo", "roughness", "metallic")}


@dataclasses.dataclass
class RadianceConfig:
    """Step-1 settings. ``preset`` 'object' uses masks (visual-hull init, mask loss);
    'scene' initialises from the dataset's points (COLMAP, or ``points3d.ply`` beside NeRF-style
    JSON), else from random points in the common view frustum, and has no mask loss."""
    preset: str = "object"
    iterations: int = 3000
    max_hits: int = 24
    sh_degree: int = 2
    sh_increase_every: int = 250          # one SH band more every this many iterations (3DGS: 1000)
    init_points: int = 20_000
    init: str = "auto"                    # auto | hull | points | random | <path.ply>
    # Hull init with surfels tangent to the shell (PCA normals): +0.6 dB at 250 its but -3 dB at
    # 500 its on spot in one 15-min run (with lambda_d2n 0.05: 25.1 dB, normal MAE 13.6 deg
    # at 1200 its), so off by default.
    init_normals: bool = False
    init_opacity: float = 0.5             # hull/points init (3DGS: 0.1); measured +2.7 dB at 300 its on spot with the shell init
    lambda_ssim: float = 0.2
    # Paper: 0.05 (2DGS from 7k of 30k its). Measured on spot (100 views, 128 px, 15 min,
    # uncontended 2 cores, ~3800 its): λ 0.05 from 600 peaked at 30.3 dB (1000 its) and then
    # collapsed (25.5 dB at 2000 its); λ 0.2 from 300 kept improving: 31.73 dB test PSNR,
    # normal MAE 5.8° at 3841 its. Short CPU schedules need the stronger, earlier prior.
    lambda_d2n: float = 0.2
    lambda_mask: float = 0.05
    d2n_from: int = 300                   # 2DGS enables the normal prior at 7k of 30k iterations
    lr_means: float = 1.6e-4              # × scene extent, decays to lr_means_final
    lr_means_final: float = 1.6e-6
    # 3DGS/2DGS rates; colour 2× faster for the short CPU schedule (larger scale/rotation
    # rates were measured to grow hazy surfels and lose ~6 dB on the spot object).
    lr_sh_dc: float = 5e-3
    lr_sh_rest: float = 5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    densify: dict | None = None           # DensityConfig fields; None: prune only (see below)
    # Largest surfel scale (σ) as a fraction of the scene extent; None: the preset's default.
    # Objects never split (see below), and without splitting a few surfels were measured to
    # grow to σ ≈ 0.17-0.3 on spot (×8-15 the median) and haze the fit from ~700 its on
    # (test PSNR 29.9 -> 19.8 dB at 1180 its); the object preset caps σ at 1 % of the extent.
    max_scale_frac: float | None = None
    eval_every: int = 250
    eval_views: int = 8
    log_every: int = 25
    checkpoint_every: int = 500
    seed: int = 0
    time_limit_s: float | None = None     # stop early (after a checkpoint) when exceeded

    def __post_init__(self):
        if self.preset not in ("object", "scene"):
            raise ValueError(f"RadianceConfig.preset must be 'object' or 'scene', got {self.preset!r}")
        if self.iterations < 1:
            raise ValueError("RadianceConfig.iterations must be ≥ 1")
        if self.sh_degree not in (0, 1, 2, 3):
            raise ValueError("RadianceConfig.sh_degree must be 0..3")
        # Both presets only prune by default (no clone/split, no opacity reset): measured
        # within CPU budgets, density control cost test PSNR. Objects (visual-hull shell,
        # spot): 27.1/26.6 dB densified vs 28.3/28.6 dB at 300/400 its. Scenes (SfM points,
        # `comgs make-dataset scene`, 1500 its): prune-only 30.4 dB; `--densify`
        # (``scaled_density_schedule``: clone/split until 750, opacity resets at 375 and 750)
        # 28.9 dB at 500 its, 20.0 dB at the end (the opacities had not recovered from the
        # reset at 750). Pass ``densify`` (DensityConfig fields over its 2DGS defaults, {} for
        # all defaults) to enable it, e.g. after a random init.
        if self.densify is None:
            self.densify = dict(max_fraction=0.0, opacity_reset_interval=10 ** 9)
        if self.max_scale_frac is None:
            # scenes: measured 20.8 vs 18.4 dB at 750 its (19.5 vs 15.6 at 1000) with σ capped
            # at 2 % of the extent vs uncapped, with clone/split (a large hazy floater formed
            # above the scene; on a version of the scene dataset with black GT pixels)
            self.max_scale_frac = 0.01 if self.preset == "object" else 0.02
        if not 0 < self.max_scale_frac <= 1.0:
            raise ValueError("RadianceConfig.max_scale_frac must be in (0, 1]")


def scaled_density_schedule(iterations: int) -> dict:
    """``RadianceConfig.densify`` for 2DGS density control on a schedule scaled to the run
    (2DGS: densify until 15k of 30k its, reset every 3k): densify until half of the run,
    reset the opacities at its quarter and half."""
    return dict(stop=max(1, iterations // 2), opacity_reset_interval=max(1, iterations // 4))


def initial_surfels(data, cfg: RadianceConfig, rng) -> tuple[SurfelParams, str]:
    """Initial surfels and a description of where they came from."""
    center, radius = data.bounds
    how = cfg.init
    has_masks = all(v.mask is not None for v in data.train)
    if how == "auto":
        how = "hull" if (cfg.preset == "object" and has_masks) else (
            "points" if data.points is not None and len(data.points) >= 4 else "random")
    if how == "hull":
        pts, cols = I.visual_hull_points(data.train, cfg.init_points, np.asarray(center), radius, rng)
        quats = I.pca_normal_quaternions(pts) if cfg.init_normals else None
        return I.surfels_from_points(pts, cols, rng, opacity=cfg.init_opacity, quats=quats), \
            f"visual-hull shell ({len(pts)} points{', PCA normals' if quats is not None else ''})"
    if how == "points":
        if data.points is None:
            raise ValueError("init='points' but the dataset has no points (use hull or random)")
        quats = I.pca_normal_quaternions(data.points) if cfg.init_normals else None
        return I.surfels_from_points(data.points, data.colors, rng, opacity=cfg.init_opacity,
                                     quats=quats), \
            f"dataset points ({len(data.points)}{', PCA normals' if quats is not None else ''})"
    if how == "random":
        if cfg.preset == "scene":
            warnings.warn("scene preset without dataset points: random initialisation, measured "
                          "at 14.1 dB test PSNR on `comgs make-dataset scene --points 0` (30.6 dB "
                          "with points); give COLMAP points or a points3d.ply", stacklevel=3)
        pts = I.frustum_points(data.train, cfg.init_points, np.asarray(center), radius, rng)
        return I.surfels_from_points(pts, None, rng), f"random, in the common view frustum ({len(pts)} points)"
    if str(how).endswith(".ply"):
        return load_ply(how), f"PLY {how}"
    raise ValueError(f"unknown init {cfg.init!r}: auto, hull, points, random or a .ply path")


def _with_sh_degree(p: SurfelParams, degree: int) -> SurfelParams:
    d = p.to_numpy()
    k = (degree + 1) ** 2
    sh = np.zeros((len(d["sh"]), k, 3), np.float32)
    m = min(k, d["sh"].shape[1])
    sh[:, :m] = d["sh"][:, :m]
    d["sh"] = sh
    return SurfelParams.from_numpy(**d)


class Trainer:
    """Owns the scene, the optimiser and the density controller of one run."""

    def __init__(self, data, run_dir, cfg: RadianceConfig, progress: bool = True):
        self.data, self.cfg, self.progress = data, cfg, progress
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.rng = np.random.default_rng(cfg.seed)
        self.extent = max(float(data.bounds[1]), 1e-6)
        resumed = ck.load_checkpoint(self.run_dir)
        if resumed is not None:
            params, moments, state = resumed
            self.iteration, self.log, self.elapsed = state["iteration"], state["log"], state["elapsed"]
            self.init_desc = state["init"]
            self.rng = np.random.default_rng(state["rng_seed"])
        else:
            params, self.init_desc = initial_surfels(data, cfg, self.rng)
            params = _with_sh_degree(params, 0)
            moments, self.iteration, self.log, self.elapsed = None, 0, [], 0.0
        self.views = data.train
        sensors = [v.camera.sensor_dict() for v in self.views] + [v.camera.sensor_dict() for v in data.test]
        targets = "color,weight,depth_unbiased,normal" if cfg.lambda_d2n > 0 else "color,weight"
        bg = 1.0 if data.white_background else 0.0
        self.scene = gbuffer_scene({"surfels": params}, sensors, max_hits=cfg.max_hits,
                                   targets=targets, background=bg)
        self.integ = self.scene.integrator()
        self.mp = mi.traverse(self.scene)
        self.mp.keep(r"surfels\..*")        # update() walks every kept key: leave the sensors out
        self.shape = self.scene.shapes()[0]
        self.opt = mi.ad.Adam(lr=1.0)
        self._register(params)
        if moments is not None:
            ck.restore_moments(self.opt, PARAM_KEYS, params, moments)
        self.density = DensityController(DensityConfig(**cfg.densify), params.count, self.extent)
        self.targets = [mi.TensorXf(v.image.astype(np.float32)) for v in self.views]
        self.masks = [None if v.mask is None else mi.TensorXf(v.mask[..., None].astype(np.float32))
                      for v in self.views]
        self._rays = {}

    # ------------------------------------------------------------- params
    def _install(self, params: SurfelParams):
        """Put every field of ``params`` (any count) into the scene; rebuilds proxies + BVH."""
        for f in field_names():
            self.mp[f"surfels.{f}"] = getattr(params, f)
        self.mp.update()

    def _register(self, params: SurfelParams):
        self._install(params)
        for f, key in PARAM_KEYS.items():
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
            "surfels.means": self._lr_means(), "surfels.sh": mi.Float(sh_lr.ravel()),
            "surfels.opacity_logit": c.lr_opacity, "surfels.log_scales": c.lr_scales,
            "surfels.quats": c.lr_quats})

    def _lr_means(self) -> float:
        c = self.cfg
        t = min(self.iteration / max(c.iterations, 1), 1.0)
        return float(self.extent * math.exp((1 - t) * math.log(c.lr_means) + t * math.log(c.lr_means_final)))

    def params(self) -> SurfelParams:
        return self.shape.params

    # ---------------------------------------------------------------- loss
    def _view_rays(self, i: int):
        if i not in self._rays:
            sensor = self.scene.sensors()[i]
            cam = (self.views + self.data.test)[i].camera
            self._rays[i] = camera_rays(sensor, cam.width, cam.height)
        return self._rays[i]

    def loss(self, i: int, img):
        c = self.cfg
        parts = self.integ.split(img)
        total = L.rgb_loss(parts["color"], self.targets[i], c.lambda_ssim)
        out = {"rgb": total}
        if c.lambda_d2n > 0 and self.iteration >= c.d2n_from:
            rays, origin = self._view_rays(i)
            d2n = L.d2n_loss(parts["normal"], parts["depth_unbiased"], parts["weight"], rays, origin)
            total = total + c.lambda_d2n * d2n
            out["d2n"] = d2n
        if c.lambda_mask > 0 and self.masks[i] is not None and self.cfg.preset == "object":
            mk = L.mask_loss(parts["weight"], self.masks[i])
            total = total + c.lambda_mask * mk
            out["mask"] = mk
        return total, out, parts

    # ---------------------------------------------------------------- step
    def step(self) -> dict:
        c = self.cfg
        it = self.iteration
        if c.sh_increase_every and it > 0 and it % c.sh_increase_every == 0 \
                and self.params().sh_degree < c.sh_degree:
            self._resize(_with_sh_degree(self.params(), self.params().sh_degree + 1), remap=None)
        i = int(self.rng.integers(len(self.views)))
        img = mi.render(self.scene, self.mp, sensor=i, seed=it)
        total, parts, bufs = self.loss(i, img)
        dr.backward(total)
        nan_grads = self._guard_gradients()
        gm = np.asarray(dr.grad(self.opt["surfels.means"]))           # [3, N]
        cam = np.asarray(self.views[i].camera.to_world)[:3, 3]
        tan_half = math.tan(math.radians(self.views[i].camera.fov_x_deg) / 2)
        self.density.accumulate(gm.T, np.asarray(self.opt["surfels.means"]).T, cam, tan_half)
        self.opt.set_learning_rate({"surfels.means": self._lr_means()})
        self.opt.step()
        self._clamp()
        self.mp.update(self.opt)
        self.iteration += 1
        stats = {k: float(np.asarray(v).ravel()[0]) for k, v in parts.items()}
        stats["loss"] = float(np.asarray(total).ravel()[0])
        c_img = np.asarray(bufs["color"])
        stats["psnr_train"] = psnr(c_img, self.views[i].image)
        stats["nan_grads"] = nan_grads
        it = self.iteration
        if self.density.due(it):
            new, counts = self.density.densify_and_prune(self.params(), self.opt,
                                                         {f: k for f, k in PARAM_KEYS.items()}, self.rng)
            self._resize(new, remap="done")
            stats.update({f"densify_{k}": v for k, v in counts.items()})
        if self.density.reset_due(it):
            new = self.density.reset_opacity(self.params(), self.opt, {"opacity_logit": "surfels.opacity_logit"})
            self.mp["surfels.opacity_logit"] = new.opacity_logit
            self.mp.update(self.opt)
        return stats

    def _guard_gradients(self) -> int:
        """Replace non-finite gradients by 0 (counted, logged) so one bad ray cannot poison Adam."""
        bad = 0
        for key in PARAM_KEYS.values():
            g = dr.grad(self.opt[key])
            ok = dr.isfinite(g)
            nb = int(dr.count(~dr.all(ok) if dr.size_v(g) > 1 else ~ok)[0])
            if nb:
                bad += nb
                dr.set_grad(self.opt[key], dr.select(ok, g, 0))
        return bad

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
    def evaluate(self, max_views: int | None = None) -> dict:
        views = self.data.test or self.data.train
        idx = np.linspace(0, len(views) - 1, min(len(views), max_views or len(views))).round().astype(int)
        off = len(self.views) if self.data.test else 0
        ps = []
        for j in np.unique(idx):
            img = mi.render(self.scene, sensor=off + int(j))
            ps.append(psnr(np.asarray(self.integ.split(img)["color"]), views[j].image))
        return {"psnr_test": float(np.mean(ps)), "views": int(len(ps))}

    def checkpoint(self):
        ck.save_checkpoint(self.run_dir, self.params(), self.opt, PARAM_KEYS, {
            "iteration": self.iteration, "log": self.log, "elapsed": self.elapsed,
            "init": self.init_desc, "rng_seed": int(self.rng.integers(1 << 31)),
            "config": dataclasses.asdict(self.cfg)})


def train_radiance(data, run_dir, cfg: RadianceConfig, progress: bool = True) -> dict:
    """Run (or resume) step 1; writes point_cloud.ply, train_log.json, psnr_vs_time.png."""
    tr = Trainer(data, run_dir, cfg, progress)
    run_dir = Path(run_dir)
    bar = None
    if progress:
        bar = tqdm(total=cfg.iterations, initial=tr.iteration, desc="step 1", unit="it", dynamic_ncols=True)
    t0 = time.perf_counter() - tr.elapsed
    stopped_early = False
    while tr.iteration < cfg.iterations:
        stats = tr.step()
        tr.elapsed = time.perf_counter() - t0
        it = tr.iteration
        if it % cfg.log_every == 0 or it == cfg.iterations or it % cfg.eval_every == 0:
            rec = {"iteration": it, "time_s": round(tr.elapsed, 3), "surfels": tr.params().count, **stats}
            if it % cfg.eval_every == 0 or it == cfg.iterations:
                t_eval = time.perf_counter()
                rec.update(tr.evaluate(cfg.eval_views))
                t0 += time.perf_counter() - t_eval        # evaluation time is not training time
            tr.log.append(rec)
            if bar is not None:
                bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{rec.get('psnr_test', stats['psnr_train']):.2f}",
                                n=tr.params().count)
        if bar is not None:
            bar.update(1)
        if it % cfg.checkpoint_every == 0:
            tr.checkpoint()
            ck.atomic_write_text(run_dir / "train_log.json", json.dumps({"summary": None, "log": tr.log}))
        if cfg.time_limit_s is not None and tr.elapsed > cfg.time_limit_s:
            stopped_early = True
            break
    if bar is not None:
        bar.close()
    tr.checkpoint()
    final = tr.evaluate()
    save_ply(tr.params(), str(run_dir / "point_cloud.ply"))
    summary = {"iterations": tr.iteration, "train_seconds": tr.elapsed, "surfels": tr.params().count,
               "init": tr.init_desc, "stopped_early": stopped_early, **final,
               "config": dataclasses.asdict(cfg)}
    ck.atomic_write_text(run_dir / "train_log.json", json.dumps({"summary": summary, "log": tr.log}, indent=1))
    plot_psnr(tr.log, run_dir / "psnr_vs_time.png")
    return summary


