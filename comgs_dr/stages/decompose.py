"""Step 2: material and lighting decomposition with SOPs (paper, "Step 2").

Continues a step-1 run folder: places and bakes Surface Octahedral Probes, then optimises
the surfels' albedo/roughness/metallic, an octahedral environment map (log radiance) and
the probe textures with

    L = L_pbr + λ_lam·L_lam + λ_sops·L_sops,
    L_pbr = L1 + 0.2·(1 − SSIM) of the deferred-PBR image (display sRGB) vs the photo,
    L_lam = L1(R, 1) + L1(M, 0),   L_sops = L1(L_in, L_tr) + L1(O, O_tr)  (baked targets).

Deviation from the paper, on purpose: the step-1 geometry is kept fixed (no λ_d2n, λ_mask
terms), so the geometry buffers of every view are traced once and cached; only material
buffers are re-rendered per iteration. ``visibility='trace'`` replaces the probes by
per-iteration ray tracing (the IRGS-style baseline) at otherwise identical settings.
A learnt map starts from the degree-2 light the training views' shading implies
(``lighting.shading_start``; the paper starts it constant, ``env_start="constant"``).

Outputs in ``out_dir`` (default ``RUN/material``): ``point_cloud.ply`` (relightable),
``envmap.exr`` (octahedral) + ``envmap_equirect.exr``, ``probes.npz``, ``train_log.json``,
``psnr_vs_time.png``, ``checkpoint.npz`` (atomic; resumed automatically).
"""
from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm.auto import tqdm

from comgs_dr.core.colorspace import display_composite, srgb_decode
from comgs_dr.core.hostarray import to_jit
from comgs_dr.emitters.octenvmap import OctEnvmapBase
from comgs_dr.eval.metrics import psnr
from comgs_dr.lighting.envmap import LOG_RANGE, OctEnvmap, oct_radiance_from_file
from comgs_dr.lighting.shading_start import light_from_shading
from comgs_dr.shading.shade import SAMPLINGS
from comgs_dr.shading.visibility import KINDS
from comgs_dr.sops.bake import bake
from comgs_dr.sops.placement import PlacementConfig, place_probes
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.surfels import load_ply, save_ply
from comgs_dr.surfels.params import object_size
from comgs_dr.surfels.scene import gbuffer_scene
from comgs_dr.surfels.shape import SurfelShapeBase
from comgs_dr.train import checkpoint as ck
from comgs_dr.train import losses as L
from comgs_dr.train.loop import TrainerBase, finish, run_loop, zero_nonfinite_grads
from comgs_dr.train.material_smoothness import material_smoothness, pairs_from_params
from comgs_dr.train.run import load_run_dataset, read_run_info


@dataclass
class MaterialConfig:
    """Step-2 settings (``comgs decompose``: every scalar field is a flag, ``--lr-env``).

    Defaults follow the paper's sec. 4.1 where it gives one (2k iterations, a 256² map
    when the capture's map is given, 5k probes of 16², offset 1 % of the object size); a
    learnt map is 32² (``LEARNT_ENV_RES``) at lr min(0.05, 15 / iterations)
    (``env_learning_rate``: the paper's 256² at 0.01 stayed flat over our 300 iterations and
    left the shading in the albedo; 0.05 over 2k diverges). Loss weights: L = L_pbr +
    lambda_lam·L_lam + lambda_sops·L_sops (module docstring), plus the white-light and
    smoothness priors (not in the paper). Learning rates per Adam step; lengths as
    fractions of the object size; times in seconds.
    Example: ``train_material(run, None, MaterialConfig(iterations=300, probe_count=2000))``.
    """
    iterations: int = 2000              # sec. 4.1: 2k
    rays: int = 128                     # S_r
    sampling: str = "auto"              # auto: uniform (the paper) while the map is learnt,
                                        # mis under a known env_file (its table fixed)
    env_res: int | None = None          # None: 256² (sec. 4.1) for a known env_file,
                                        # LEARNT_ENV_RES for a learnt map
    env_init: float = 0.5               # initial constant radiance (env_start constant)
    env_start: str = "shading"          # a learnt map's start: shading (the degree-2 light
                                        # the training views' shading implies,
                                        # lighting.shading_start; not in the paper) or
                                        # constant (env_init, the paper)
    env_file: str | None = None         # the capture's light when it is known (an HDRI shot
                                        # on set, a synthetic capture's map): kept fixed
    env_scale: float = 1.0              # × env_file's radiance
    probe_count: int = 5000             # sec. 4.1: 5k
    probe_res: int = 16                 # sec. 4.1: 16²
    probe_offset: float = 0.01          # × object size (sec. 4.1: 1 %)
    probe_k: int = 8
    bake_hits: int = 32
    bake_supersample: int = 1
    visibility: str = "sops"            # sops | trace | none
    indirect: bool = True
    trace_hits: int = 32
    trace_offset: float = 0.01          # × object size: visibility-ray origin offset
    lr_env: float | None = None         # None: env_learning_rate, min(0.05, 15 / iterations)
                                        # (sec. 4.1: 0.01 over 2k iterations)
    lr_material: float = 0.01
    lr_sops: float = 0.001
    lambda_lam: float = 0.001
    lambda_sops: float = 1.0
    lambda_ssim: float = 0.2
    lambda_white: float = 0.1           # neutral-light prior on the map's mean colour (not in
                                        # the paper): albedo and light colour are ambiguous
    lambda_smooth: float | None = None  # edge-aware material smoothness over the surfels'
                                        # neighbours (train.material_smoothness; not in the
                                        # paper); None: SMOOTH_DEFAULT 0.1, learnt or known light
    smooth_k: int = 8
    smooth_sigma: float = 0.1           # step-1 colour difference that unties two neighbours
    init_albedo: float = 0.5
    init_roughness: float = 0.5
    init_metallic: float = 0.0
    min_roughness: float = 0.04
    max_hits: int = 32
    eval_every: int = 100
    eval_views: int = 6
    log_every: int = 10
    checkpoint_every: int = 200
    checkpoint_every_s: float | None = 300.0   # also by wall time; SIGINT/SIGTERM write one too
    seed: int = 0
    time_limit_s: float | None = None

    def __post_init__(self):
        if self.env_res is not None and int(self.env_res) < 2:
            raise ValueError(f"MaterialConfig.env_res must be ≥ 2, got {self.env_res!r}")
        if self.lr_env is not None and not (np.isfinite(self.lr_env) and self.lr_env >= 0):
            raise ValueError(f"MaterialConfig.lr_env must be finite and ≥ 0, got {self.lr_env!r}")
        if self.visibility not in KINDS:
            raise ValueError(f"MaterialConfig.visibility must be sops, trace or none, got "
                             f"{self.visibility!r}")
        if self.sampling not in SAMPLINGS + ("auto",):
            raise ValueError(f"MaterialConfig.sampling must be auto or one of "
                             f"{', '.join(SAMPLINGS)}, got {self.sampling!r}")
        if self.env_start not in ENV_STARTS:
            raise ValueError(f"MaterialConfig.env_start must be one of {', '.join(ENV_STARTS)}, "
                             f"got {self.env_start!r}")
        if self.iterations < 1 or self.rays < 1:
            raise ValueError("MaterialConfig: iterations and rays must be ≥ 1")
        if self.lambda_smooth is not None and not (np.isfinite(self.lambda_smooth)
                                                   and self.lambda_smooth >= 0):
            raise ValueError(f"MaterialConfig.lambda_smooth must be finite and ≥ 0, got "
                             f"{self.lambda_smooth!r}")
        if not (np.isfinite(self.env_scale) and self.env_scale > 0):
            raise ValueError(f"MaterialConfig.env_scale must be finite and > 0, got "
                             f"{self.env_scale!r}")


ENV_STARTS = ("shading", "constant")
CKPT_FORMAT = "comgs_dr.material_checkpoint/2"
SMOOTH_DEFAULT = 0.1           # lambda_smooth's default (docs/composite.md, "Sparkles")
# A learnt capture light must take the shading's direction before the albedo does. Each
# surfel's albedo is its own Adam variable and explains its pixels' brightness within a few
# steps; the shared map only gets what is left. With the paper's 256² map at lr 0.01 and our
# 300 iterations (the paper: 2k), the learnt studio stayed flat (irradiance max/min over
# normals 1.33 against the true map's 13.7) and the albedo took the shading (its log
# luminance 1.35× the step-1 colour's): a pale, blotchy relit object. A 32² map at lr 0.05
# learns the light's direction (docs/composite.md, "The object's blotches"); the rate
# shrinks over longer runs (env_learning_rate).
LEARNT_ENV_RES = 32
KNOWN_ENV_RES = 256            # sec. 4.1: a given map keeps its softboxes
MAX_LR_ENV = 0.05              # the learnt map's rate over short runs (300 iterations)
ENV_LOG_BUDGET = 15.0          # ... and its log-radiance steps in all: 0.0075 over 2k


def env_resolution(cfg: MaterialConfig) -> int:
    """The map's texels per side: ``cfg.env_res``, or (None) ``KNOWN_ENV_RES`` for a given
    ``env_file`` and ``LEARNT_ENV_RES`` for a learnt map."""
    if cfg.env_res is not None:
        return int(cfg.env_res)
    return KNOWN_ENV_RES if cfg.env_file is not None else LEARNT_ENV_RES


def env_learning_rate(cfg: MaterialConfig) -> float:
    """The map's Adam rate: ``cfg.lr_env``, or (None) ``ENV_LOG_BUDGET`` / iterations, at most
    ``MAX_LR_ENV``: a short run needs a fast map, and a long one at that rate diverges (300
    iterations at 0.05: test PSNR 26.14 dB; 2000 at 0.05: 26.39 at 400, then a hot texel
    and 15.90 at the end)."""
    if cfg.lr_env is not None:
        return float(cfg.lr_env)
    return min(MAX_LR_ENV, ENV_LOG_BUDGET / max(int(cfg.iterations), 1))


MAT_KEYS = ("surfels.albedo", "surfels.roughness", "surfels.metallic")
ENV_KEY, SOPS_KEY = "env.theta", "integrator.probe_data"


class MaterialTrainer(TrainerBase):
    """Step 2's :class:`~comgs_dr.train.loop.TrainerBase`, a Mitsuba optimisation:
    ``mi.render`` of the ``sop_pbr`` integrator (lit by an ``octenvmap`` emitter) +
    ``dr.backward``, with Adam on
    ``mi.traverse(scene)`` keys: the surfels' materials, the probe textures
    (``integrator.probe_data``) and the map's log radiance θ (``env.data = exp θ``, a
    latent variable: scale-free steps, HDR without overflow).

    While it learns the map, training keeps the paper's uniform-hemisphere estimator
    (``MaterialConfig.sampling`` ``auto``): the map starts smooth (the degree-2 light of
    the shading start, or constant), where importance sampling gains little over uniform
    directions on the sphere (half the samples below the horizon), and its table would be
    rebuilt every step; each pixel gets its own rotation of the Hammersley set. Under a
    known map (``env_file``, kept fixed) it uses MIS, as rendering (relight, the plugin)
    does.
    """

    def __init__(self, run_dir, out_dir=None, cfg: MaterialConfig = MaterialConfig(),
                 progress: bool = True, data=None):
        self.cfg, self.progress = cfg, progress
        self.env_res = env_resolution(cfg)
        self.run_dir = Path(run_dir)
        self.out_dir = Path(out_dir) if out_dir else self.run_dir / "material"
        self.out_dir.mkdir(parents=True, exist_ok=True)
        info = read_run_info(self.run_dir)
        ply = self.run_dir / "point_cloud.ply"
        if not ply.exists():
            raise FileNotFoundError(f"{ply} not found: finish step 1 first (`comgs reconstruct`)")
        self.data = data if data is not None else load_run_dataset(self.run_dir, info)
        self.bg = 1.0 if self.data.white_background else 0.0
        self.rng = np.random.default_rng(cfg.seed)
        params = load_ply(str(ply))
        resumed = self._load_checkpoint()
        n = params.count
        if resumed is None:
            params.albedo = to_jit(mi.Color3f, np.full((3, n), cfg.init_albedo, np.float32))
            params.roughness = to_jit(mi.Float, np.full(n, cfg.init_roughness, np.float32))
            params.metallic = to_jit(mi.Float, np.full(n, cfg.init_metallic, np.float32))
        self.views, self.test = self.data.train, self.data.test
        clip = self.data.clip_planes()            # relative to the scene, as step 1
        sensors = [v.camera.sensor_dict(**clip) for v in self.views + self.test]
        self.object_size = object_size(params)
        # a known (fixed) map is importance-sampled: its table is built once, and uniform
        # directions rarely hit a studio's small softboxes, whose light then goes missing
        self.sampling = (("mis" if cfg.env_file is not None else "uniform")
                         if cfg.sampling == "auto" else cfg.sampling)
        self._pairs = None
        # the smoothness prior by default under a known and a learnt light: without it a
        # dielectric's surfels come out partly metallic with scattered roughness, which the
        # relit object shows as sparkles (it cannot resolve the learnt light's colour split)
        self.lambda_smooth = SMOOTH_DEFAULT if cfg.lambda_smooth is None else cfg.lambda_smooth
        if self.lambda_smooth > 0:
            i, j, w = pairs_from_params(params, k=cfg.smooth_k, sigma=cfg.smooth_sigma)
            self._pairs = (mi.UInt32(i), mi.UInt32(j), mi.Float(w))
        self.timings = {}
        probe_path = None
        if cfg.visibility == "sops":
            probe_path = self._make_probes(params, sensors)
        self.shape = SurfelShapeBase.from_params(params, id="surfels")
        integ = {"type": "sop_pbr", "visibility": cfg.visibility, "rays": cfg.rays,
                 "sampling": self.sampling, "indirect": cfg.indirect, "hide_emitters": True,
                 "max_hits": cfg.max_hits, "trace_hits": cfg.trace_hits, "probe_k": cfg.probe_k,
                 "trace_offset": cfg.trace_offset * self.object_size}
        if probe_path is not None:
            integ["probes"] = str(probe_path)
        scene = {"type": "scene", "surfels": self.shape, "integrator": integ,
                 "env": OctEnvmapBase.from_radiance(np.full((self.env_res,) * 2 + (3,), cfg.env_init),
                                                    id="env")}
        for i, sd in enumerate(sensors):
            scene[f"sensor_{i:03d}"] = {**sd, "film": {**sd["film"], "pixel_format": "rgba"}}
        self.scene = mi.load_dict(scene)
        self.integrator = self.scene.integrator()
        self.mp = mi.traverse(self.scene)
        self.mp.keep(r"surfels\.(albedo|roughness|metallic)|env\.data|integrator\.probe_data")
        self.opt = mi.ad.Adam(lr=cfg.lr_material)
        for k in MAT_KEYS:
            self.opt[k] = self.mp[k]
        self.env_fixed = cfg.env_file is not None
        self.opt[ENV_KEY] = to_jit(mi.Float, np.log(self._initial_env()).astype(np.float32).ravel())
        lrs = {ENV_KEY: 0.0 if self.env_fixed else env_learning_rate(cfg)}
        self.has_sops = cfg.visibility == "sops"
        if self.has_sops:
            self.opt[SOPS_KEY] = self.mp[SOPS_KEY]
            lrs[SOPS_KEY] = cfg.lr_sops
            self.sops_target = mi.TensorXf(self.mp[SOPS_KEY])      # baked L_tr, O_tr
            is_occ = (dr.arange(mi.UInt32, dr.width(self.sops_target.array)) % 4) == 3
            self._sops_is_occ = is_occ
            self._sops_w = dr.select(is_occ, 1.0, 1.0 / 3.0)
        self.opt.set_learning_rate(lrs)
        self.iteration, self.elapsed, self.log = 0, 0.0, []
        self.nonfinite_total = 0
        if resumed is not None:
            self._restore(resumed)
        self._apply()
        self.targets = [to_jit(mi.TensorXf, v.image) for v in self.views]
        t0 = time.perf_counter()
        for j in tqdm(range(len(self.views) + len(self.test)), desc="G-buffers", unit="view",
                      disable=not progress):
            self.integrator.shading_points(self.scene, j)   # fixed geometry: traced once per view
        self.timings["gbuffers_s"] = time.perf_counter() - t0
        self.light_start = {"start": "file" if self.env_fixed else
                            "resumed" if resumed is not None else cfg.env_start}
        if self.light_start["start"] == "shading":
            self._start_light_from_shading(lrs)
        dr.eval()

    def _initial_env(self) -> np.ndarray:
        """[R, R, 3] octahedral radiance to start from: ``env_init`` everywhere, or the
        known capture light ``env_file`` (equirect in the package's Z-up convention, as
        ``relight`` reads it, or our octahedral EXR) × ``env_scale``, resampled to ``env_res``.
        Under an unknown light a diffuse colour fits as albedo × light colour for any split;
        a known light removes the ambiguity, and it stays fixed."""
        c = self.cfg
        r = self.env_res
        if c.env_file is None:
            return np.full((r, r, 3), c.env_init, np.float64)
        rad = oct_radiance_from_file(c.env_file, r, c.env_scale)   # [R, R, 3]; NaN: ValueError
        lo, hi = np.exp(LOG_RANGE[0]), np.exp(LOG_RANGE[1])
        if rad.max() > hi:
            raise ValueError(f"MaterialConfig.env_file {c.env_file}: radiance up to "
                             f"{rad.max():.3g} exceeds the map's range ({hi:.3g}); lower env_scale")
        return np.maximum(rad, lo)

    def _start_light_from_shading(self, lrs: dict):
        """The learnt map starts as the degree-2 light the training views' shading implies
        (``lighting.shading_start``: the fully covered pixels' linear colour against their
        G-buffer normals, at the albedo ``init_albedo`` the surfels start from). A view set
        too small for the fit keeps the constant start, said in a warning and in the
        summary's ``light_start``."""
        ns, cs = [], []
        for j, v in enumerate(self.views):
            _, geo = self.integrator.shading_points(self.scene, j)
            if not len(geo["pix_np"]):
                continue
            full = geo["W_np"].ravel()[geo["pix_np"]] > 0.99
            n = np.asarray(geo["n"], np.float64).T                      # [P, 3]
            img = np.asarray(v.image, np.float64)
            img = img.reshape(-1, img.shape[-1])[geo["pix_np"][full], :3]
            ns.append(n[full])
            cs.append(srgb_decode(np.clip(img, 0.0, 1.0)))
        try:
            rad, info = light_from_shading(np.concatenate(ns) if ns else np.zeros((0, 3)),
                                           np.concatenate(cs) if cs else np.zeros((0, 3)),
                                           self.env_res, self.cfg.init_albedo)
        except ValueError as e:
            warnings.warn(f"step 2: the learnt light starts constant ({e})", stacklevel=2)
            self.light_start = {"start": "constant", "reason": str(e)}
            return
        lo, hi = np.exp(LOG_RANGE[0]), np.exp(LOG_RANGE[1])
        self.opt[ENV_KEY] = to_jit(mi.Float, np.log(np.clip(rad, lo, hi)).astype(np.float32).ravel())
        self.opt.set_learning_rate(lrs)
        self._apply()
        self.light_start.update(info)

    # ------------------------------------------------------------------ probes
    def _make_probes(self, params, sensors) -> Path:
        path = self.out_dir / "probes_init.npz"
        if path.exists():
            return path
        t0 = time.perf_counter()
        cams = [v.camera for v in self.views]
        probes = place_probes(params, cams, PlacementConfig(
            count=self.cfg.probe_count, res=self.cfg.probe_res,
            offset_frac=self.cfg.probe_offset, max_hits=self.cfg.max_hits),
            object_size=self.object_size, seed=self.cfg.seed)
        t1 = time.perf_counter()
        bake(gbuffer_scene({"surfels": params}, sensors[:1], targets="weight"), probes,
             self.cfg.bake_hits, self.cfg.bake_supersample, progress=self.progress)
        t2 = time.perf_counter()
        self.timings.update(placement_s=t1 - t0, bake_s=t2 - t1)
        probes.meta["timings"] = {"placement_s": t1 - t0, "bake_s": t2 - t1}
        probes.save(path)
        return path

    # ------------------------------------------------------------------ step
    def _apply(self):
        """Optimiser variables -> scene parameters (env.data = exp θ)."""
        r = self.env_res
        if not (self.env_fixed and getattr(self, "_env_set", False)):   # a fixed map: once,
            e = dr.exp(self.opt[ENV_KEY])                               # and out of the graph
            self.mp["env.data"] = mi.TensorXf(dr.detach(e) if self.env_fixed else e,
                                              shape=(r, r, 3))
            self._env_set = True
        self.mp.update(self.opt)

    def render(self, i, seed=0, grad=True):
        """Display-sRGB image of view ``i`` (train views, then test views)."""
        img = mi.render(self.scene, self.mp if grad else None, sensor=i, seed=seed,
                        seed_grad=seed + (1 << 20))
        return display_composite(img, self.bg)

    def step(self) -> dict:
        c = self.cfg
        i = int(self.rng.integers(len(self.views)))
        t0 = time.perf_counter()
        self._apply()
        img = self.render(i, seed=self.iteration)
        loss = L.rgb_loss(img, self.targets[i], c.lambda_ssim)
        stats = {}
        if c.lambda_lam > 0:
            pts, _ = self.integrator.shading_points(self.scene, i)
            # 1/P as an opaque variable: a literal would recompile the backward per view
            inv_p = dr.opaque(mi.Float, 1.0 / max(pts.count, 1))
            lam = (dr.sum(dr.abs(pts.roughness - 1.0)) + dr.sum(pts.metallic)) * inv_p
            loss = loss + c.lambda_lam * lam
        if self.has_sops and c.lambda_sops > 0:
            # L1(L_in, L_tr) + L1(O, O_tr): channel weights 1/3,1/3,1/3,1, mean × 4
            lsops = 4.0 * dr.mean(self._sops_w * dr.abs(self.opt[SOPS_KEY].array - self.sops_target.array))
            loss = loss + c.lambda_sops * lsops
            stats["sops"] = float(lsops[0])
        if self._pairs is not None:
            ls = material_smoothness(self.opt["surfels.albedo"], self.opt["surfels.roughness"],
                                     self.opt["surfels.metallic"], *self._pairs)
            loss = loss + self.lambda_smooth * ls
            stats["smooth"] = float(ls[0])
        if c.lambda_white > 0 and not self.env_fixed:
            lw = self._white_prior()
            loss = loss + c.lambda_white * lw
            stats["white"] = float(lw[0])
        dr.eval(loss, img)
        dr.sync_thread()
        t1 = time.perf_counter()
        dr.backward(loss)
        bad = self._guard_gradients()
        dr.sync_thread()
        t2 = time.perf_counter()
        self.opt.step()
        self._clamp()
        self._apply()
        dr.eval()
        dr.sync_thread()
        t3 = time.perf_counter()
        self.iteration += 1
        stats.update(loss=float(loss[0]), psnr_train=psnr(np.asarray(img), self.views[i].image),
                     t_render=t1 - t0, t_backward=t2 - t1, t_step=t3 - t2)
        if bad:
            stats["nonfinite_grads"] = bad
        return stats

    def _white_prior(self):
        """Σ_t w_t Σ_c (log e_tc − mean_c log e_t)²: the log-chroma (saturation) of every
        texel t of the map, weighted by its share of the power w_t (detached), so that the
        lights count most. Under distant light a diffuse colour fits as albedo × light
        colour for any split, so without a prior an object's colour can move into the light
        (and relit, the object loses it); a prior on the map's mean colour alone lets one
        light take the colour and another its complement. Lights are rarely saturated: the
        prior prefers grey ones (a white-light prior, not in the paper)."""
        e = dr.exp(self.opt[ENV_KEY])                                           # [R·R·3]
        n = dr.width(e) // 3
        idx = dr.arange(mi.UInt32, n) * 3
        rgb = [dr.gather(mi.Float, e, idx + c) for c in range(3)]               # 3 × [R·R]
        logs = [dr.log(dr.maximum(x, 1e-12)) for x in rgb]
        mu = (logs[0] + logs[1] + logs[2]) / 3.0
        lum = dr.detach(rgb[0] + rgb[1] + rgb[2])
        w = lum / dr.maximum(dr.sum(lum), 1e-12)
        return dr.sum(w * sum((l - mu) ** 2 for l in logs))

    def _guard_gradients(self) -> int:
        """Non-finite gradient entries are zeroed (never applied), counted and reported."""
        bad = zero_nonfinite_grads(self.opt, list(self.opt.keys()))
        if bad:
            self.nonfinite_total += bad
            warnings.warn(f"step 2, iteration {self.iteration}: {bad} non-finite gradient "
                          "entries zeroed (not applied)", stacklevel=2)
        return bad

    def _clamp(self):
        c = self.cfg
        o = self.opt
        o["surfels.albedo"] = dr.clip(o["surfels.albedo"], 0.0, 1.0)
        o["surfels.roughness"] = dr.clip(o["surfels.roughness"], c.min_roughness, 1.0)
        o["surfels.metallic"] = dr.clip(o["surfels.metallic"], 0.0, 1.0)
        o[ENV_KEY] = dr.clip(o[ENV_KEY], *LOG_RANGE)
        if self.has_sops:
            a = o[SOPS_KEY]
            o[SOPS_KEY] = mi.TensorXf(dr.select(self._sops_is_occ, dr.clip(a.array, 0.0, 1.0),
                                                dr.maximum(a.array, 0.0)), a.shape)

    # ------------------------------------------------------------------ eval / io
    def evaluate(self, max_views: int | None = None) -> dict:
        vs = self.test or self.views
        n = len(vs) if max_views is None else min(max_views, len(vs))
        off = len(self.views) if self.test else 0
        ps = []
        for j in np.linspace(0, len(vs) - 1, n).round().astype(int):
            with dr.suspend_grad():
                img = self.render(off + int(j), seed=12345, grad=False)
            ps.append(psnr(np.asarray(img), vs[j].image))
        return {"psnr_test": float(np.mean(ps))}

    def materials(self) -> dict:
        return {"albedo": self.opt["surfels.albedo"], "roughness": self.opt["surfels.roughness"],
                "metallic": self.opt["surfels.metallic"]}

    def env_radiance(self) -> np.ndarray:
        r = self.env_res
        return np.exp(np.array(dr.detach(self.opt[ENV_KEY]), np.float64)).reshape(r, r, 3)

    def _keys(self) -> dict:
        return {k: k for k in list(MAT_KEYS) + [ENV_KEY] + ([SOPS_KEY] if self.has_sops else [])}

    @property
    def checkpoint_path(self) -> Path:
        return self.out_dir / ck.CKPT_NAME

    def checkpoint(self):
        ck.save_checkpoint(self.checkpoint_path, CKPT_FORMAT,
                           {k: np.asarray(self.opt[k]) for k in self._keys()}, self.opt,
                           self._keys(), {"iteration": self.iteration, "elapsed": self.elapsed,
                                          "log": self.log, "config": dataclasses.asdict(self.cfg),
                                          "rng_state": self.rng.bit_generator.state})

    def _load_checkpoint(self):
        p = self.out_dir / ck.CKPT_NAME
        resumed = ck.load_checkpoint(p, CKPT_FORMAT)
        if resumed is not None and resumed[2]["config"].get("visibility") != self.cfg.visibility:
            raise ValueError(f"checkpoint {p} was made with visibility "
                             f"{resumed[2]['config'].get('visibility')!r}, not {self.cfg.visibility!r}")
        if resumed is not None:
            saved = resumed[2]["config"]
            res = saved.get("env_res") or (KNOWN_ENV_RES if saved.get("env_file") else LEARNT_ENV_RES)
            if int(res) != self.env_res:    # a run from before LEARNT_ENV_RES: 256²
                raise ValueError(f"checkpoint {p} holds a {res}² environment map, not "
                                 f"{self.env_res}²: resume with --env-res {res}, or start a "
                                 f"new --out folder")
        return resumed

    @staticmethod
    def _from_numpy(name, a, like):
        if isinstance(like, mi.TensorXf):
            return to_jit(mi.TensorXf, np.reshape(a, like.shape))
        return to_jit(type(like), a)

    def _restore(self, resumed):
        arrays, moments, state = resumed
        for k in self._keys():
            self.opt[k] = self._from_numpy(k, arrays[k], self.opt[k])
        ck.restore_moments(self.opt, self._keys(), moments, self._from_numpy)
        self.iteration, self.elapsed, self.log = state["iteration"], state["elapsed"], state["log"]
        if "rng_state" in state:
            self.rng.bit_generator.state = state["rng_state"]

    def save_outputs(self) -> dict:
        self._apply()
        save_ply(self.shape.params, str(self.out_dir / "point_cloud.ply"))
        env = OctEnvmap(self.env_radiance())
        env.save(self.out_dir / "envmap.exr")
        env.save(self.out_dir / "envmap_equirect.exr", equirect_width=4 * env.res)
        paths = {"ply": "point_cloud.ply", "envmap": "envmap.exr"}
        if self.has_sops:
            probes = ProbeSet.load(self.out_dir / "probes_init.npz")
            probes.texture = np.array(dr.detach(self.opt[SOPS_KEY]), np.float32).reshape(probes.texture.shape)
            probes.save(self.out_dir / "probes.npz")
            paths["probes"] = "probes.npz"
        return paths


def train_material(run_dir, out_dir=None, cfg: MaterialConfig = MaterialConfig(),
                   progress: bool = True, data=None) -> dict:
    """Run (or resume) step 2; returns the summary written to ``train_log.json``."""
    tr = MaterialTrainer(run_dir, out_dir, cfg, progress, data)
    stopped_early = run_loop(tr, cfg, f"step 2 ({cfg.visibility})", progress,
                             jsonl_dir=tr.out_dir, stage="decompose")
    final = tr.evaluate()
    paths = tr.save_outputs()
    its = [r for r in tr.log if "t_render" in r]
    split = {k: float(np.median([r[k] for r in its])) for k in
             ("t_render", "t_backward", "t_step")} if its else {}
    summary = {"iterations": tr.iteration, "train_seconds": tr.elapsed,
               "stopped_early": stopped_early, **final, "median_step_split_s": split,
               "setup_timings_s": tr.timings, "outputs": paths,
               "nonfinite_gradients": tr.nonfinite_total,
               "probes": ProbeSet.load(tr.out_dir / "probes.npz").count if tr.has_sops else None,
               "env_res": tr.env_res, "lr_env": env_learning_rate(cfg),
               "light_start": tr.light_start,
               "config": dataclasses.asdict(cfg)}
    return finish(tr, tr.out_dir, summary, stage="decompose")
