"""Relighting and evaluation of a step-2 (material) run.

``relight_run`` renders the relightable surfels under a new environment map with deferred
PBR. Occlusion comes from the run's probes (or tracing); the probes' baked/optimised
*indirect radiance* belongs to the training illumination, so it is dropped under a new
map (``indirect=False``) unless the map is the training one.

Metrics (per view, averaged), when the dataset holds the ground truth that
``comgs make-dataset object`` writes:

* relighting PSNR/SSIM vs ``test_relight/<map stem>/r_<i>.exr`` (display sRGB, composited
  over the run's background like the training photos);
* albedo PSNR after per-channel median scale alignment (TensoIR protocol: s_c =
  median(gt_c / pred_c) over covered pixels), computed on sRGB-encoded albedo, and the
  albedo's colour bias before it: ``albedo_ratio_{r,g,b}`` = 1 / s_c (1: right; unequal
  channels: the light/albedo split moved colour between them);
* normal MAE (degrees) of the shading normals vs ``r_<i>_normal.exr``.

Beside each view's PNG an EXR (:func:`material_layers`) holds the linear RGBA render and the
G-buffer: depth, normal, albedo, roughness, metallic.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from comgs_dr.core import exr, runlog
from comgs_dr.core.cameras import camera_rays
from comgs_dr.core.colorspace import display_composite, srgb_encode
from comgs_dr.data.images import write_png8
from comgs_dr.data.nerf import split_frames
from comgs_dr.eval import metrics as M
from comgs_dr.shading.shade import SAMPLINGS
from comgs_dr.shading.visibility import KINDS
from comgs_dr.surfels import load_ply
from comgs_dr.surfels.edit import (
    MaterialEdit,
    edit_materials,
    parse_mask_spec,
    parse_material_spec,
)
from comgs_dr.surfels.params import object_size
from comgs_dr.surfels.shape import SurfelShapeBase
from comgs_dr.train import checkpoint as ck
from comgs_dr.train.run import load_run_dataset, read_run_info, select_views


def align_albedo(pred, gt, mask):
    """Per-channel median scale of ``pred`` [H,W,3] to ``gt`` over ``mask`` [H,W] (bool)."""
    m = mask & (pred.min(-1) > 1e-4)
    if m.sum() < 10:
        return pred, np.ones(3)
    s = np.array([np.median(gt[..., c][m] / pred[..., c][m]) for c in range(3)])
    return pred * s, s


def _display(x):
    """Display sRGB of linear values, clipped to [0, 1] first."""
    return srgb_encode(np.clip(x, 0.0, 1.0))


MATERIAL_ATTRS = {"colour": "linear sRGB (Rec. 709 primaries), premultiplied by A = coverage",
                  "depth": "ray distance from the near-clip origin, 0 where uncovered",
                  "normal": "unit world-space shading normal, 0 where uncovered",
                  "materials": "albedo (linear), roughness, metallic: blended per pixel, "
                               "not premultiplied, 0 where uncovered"}


def material_layers(rgba, pts, geo, sensor) -> dict:
    """EXR layers of one relit view: '' = linear premultiplied RGBA [H, W, 4] (``rgba``),
    'depth', 'normal', 'albedo', 'roughness', 'metallic' scattered from the shading points
    ``pts`` of the covered pixels ``geo['pix_np']`` (0 elsewhere)."""
    h, w = geo["shape"]
    pix = geo["pix_np"]
    dirs, origins = camera_rays(sensor)
    d = np.asarray(dirs, np.float64).reshape(-1, 3)[pix]                       # [P, 3]
    o = np.asarray(origins, np.float64).reshape(-1, 3)[pix]
    x = np.asarray(pts.position, np.float64).T                                 # [P, 3]

    def grid(v):                                                               # [P, c] -> [H, W, c]
        out = np.zeros((h * w, v.shape[1]))
        out[pix] = v
        return out.reshape(h, w, -1)
    return {"": np.asarray(rgba, np.float64), "depth": grid(((x - o) * d).sum(-1)[:, None]),
            "normal": grid(np.asarray(geo["n"], np.float64).T),
            "albedo": grid(np.asarray(pts.albedo, np.float64).T),
            "roughness": grid(np.asarray(pts.roughness, np.float64)[:, None]),
            "metallic": grid(np.asarray(pts.metallic, np.float64)[:, None])}


VIEWS = ("test", "train")


@dataclass
class RelightConfig:
    """Settings of :func:`relight_run` (``comgs relight``).

    views: which split to render, ``test`` (default) or ``train``; max_views: at most this
    many, evenly spread (None: all). rays: S_r, light samples per shading point (default
    256). sampling: the estimator, ``mis`` (env-map + BRDF importance sampling, default) or
    ``uniform`` (the paper's training estimator) or ``cosine``. visibility: ``sops`` /
    ``trace`` / ``none`` (None: the step-2 run's). indirect: the probes' indirect radiance
    (None: only when the map is the one the dataset was captured under, since it holds the
    training light). envmap_scale: × the map's radiance (default 1). envmap_res: side of
    the octahedral map (None: an equirect map's height, at most 1024).

    material: an edit of the object's material before relighting, comma-separated
    ``albedo=R,G,B`` (linear) or ``scale=S[,S,S]``, ``roughness=X``, ``metallic=Y``
    (``surfels.edit.parse_material_spec``); material_mask: the surfels it applies to,
    ``box:x0,y0,z0,x1,y1,z1`` (world) or a file of surfel indices (default: all).

    Example: ``relight_run(run, "sky.exr", cfg=RelightConfig(rays=64, max_views=4))``.
    """
    views: str = "test"
    rays: int = 256
    sampling: str = "mis"
    visibility: str | None = None
    indirect: bool | None = None
    envmap_scale: float = 1.0
    envmap_res: int | None = None
    max_views: int | None = None
    material: str | None = None
    material_mask: str | None = None

    def __post_init__(self):
        if self.views not in VIEWS:
            raise ValueError(f"RelightConfig.views must be test or train, got {self.views!r}")
        if self.sampling not in SAMPLINGS:
            raise ValueError(f"RelightConfig.sampling must be one of {', '.join(SAMPLINGS)}, "
                             f"got {self.sampling!r}")
        if self.visibility is not None and self.visibility not in KINDS:
            raise ValueError(f"RelightConfig.visibility must be None or one of "
                             f"{', '.join(KINDS)}, got {self.visibility!r}")
        if self.material_mask and not self.material:
            raise ValueError("RelightConfig.material_mask needs material (--material-mask "
                             "needs --material)")
        if self.material:
            parse_material_spec(self.material)                     # a bad spec: ValueError

    def edit(self) -> MaterialEdit | None:
        """The parsed ``material`` edit (None: no edit)."""
        return parse_material_spec(self.material) if self.material else None


def relight_run(run_dir, envmap, material_dir=None, *, cfg: RelightConfig | None = None,
                out_dir=None, progress: bool = True, edit: MaterialEdit | None = None,
                edit_mask=None, **overrides) -> dict:
    """Render ``cfg.views`` of a finished step-2 run under ``envmap`` with ``mi.render`` of
    the ``sop_pbr`` integrator lit by an ``octenvmap`` emitter; optional material ``edit``
    (whole object or ``edit_mask``; or ``cfg.material`` / ``cfg.material_mask`` specs);
    writes PNGs, per-view EXRs (:func:`material_layers`) + ``metrics.json``.

    ``material_dir``: the step-2 folder (default ``run_dir/material``); ``out_dir``: default
    ``<material_dir>/relight_<map stem>_<views>``; ``overrides``: RelightConfig fields
    (``relight_run(run, env, rays=64)``)."""
    cfg = dataclasses.replace(cfg or RelightConfig(), **overrides)
    if cfg.material and edit is not None:
        raise ValueError("relight_run: give the edit as edit= or as cfg.material, not both")
    run_dir = Path(run_dir)
    mdir = Path(material_dir) if material_dir else run_dir / "material"
    summary, info, data = _material_run(run_dir, mdir)
    vs = select_views(data.test if cfg.views == "test" else data.train, cfg.max_views)
    params = load_ply(str(mdir / "point_cloud.ply"))
    if cfg.material:
        edit, edit_mask = cfg.edit(), parse_mask_spec(cfg.material_mask, params.count)
    if edit is not None and not edit.empty:
        params = edit_materials(params, edit, edit_mask)
    env_path = Path(envmap)
    kind = cfg.visibility or summary["config"]["visibility"]
    same_light = _captured_under(env_path, info)
    use_indirect = same_light if cfg.indirect is None else cfg.indirect
    scene = mi.load_dict(_scene_dict(params, env_path, mdir, summary, vs, data, cfg, kind,
                                     use_indirect))
    bg = 1.0 if data.white_background else 0.0
    out = Path(out_dir) if out_dir else mdir / f"relight_{env_path.stem}_{cfg.views}"
    out.mkdir(parents=True, exist_ok=True)
    truth = _Truth(Path(info["data"]), info["resolution_scale"] == 1,
                   Path(info["data"]) / f"{cfg.views}_relight" / env_path.stem,
                   {Path(fr["file_path"]).name: fr for fr in split_frames(info["data"], cfg.views)})
    per_view = [_relight_view(scene, i, vs[i], out, bg, truth)
                for i in tqdm(range(len(vs)), desc=f"relight {env_path.stem}", unit="view",
                              disable=not progress)]
    keys = sorted({k for r in per_view for k in r if k != "view"})
    res = {k: float(np.mean([r[k] for r in per_view if k in r])) for k in keys}
    res.update(envmap=str(env_path), views=len(vs), indirect=use_indirect, visibility=kind,
               rays=cfg.rays, sampling=cfg.sampling, envmap_res=scene.environment().res,
               edit=None if edit is None else dataclasses.asdict(edit), per_view=per_view)
    ck.atomic_write_text(out / "metrics.json", json.dumps(runlog.json_safe(res), indent=1,
                                                           allow_nan=False))
    return res


def _material_run(run_dir: Path, mdir: Path):
    """(step 2's summary, the run info, the dataset's cameras) of a finished step-2 run."""
    log = mdir / "train_log.json"
    if not log.exists():
        raise FileNotFoundError(f"{log} not found: run `comgs decompose {run_dir}` first")
    summary = json.loads(log.read_text())["summary"]
    info = read_run_info(run_dir)
    data = load_run_dataset(run_dir, info, pixels=False)       # cameras only
    return summary, info, data


def _captured_under(env_path: Path, info: dict) -> bool:
    """Whether ``env_path`` is the map the run's dataset was captured under (its meta.json)."""
    meta = Path(info["data"]) / "meta.json"
    return env_path.resolve() == Path(json.loads(meta.read_text()).get("envmap", "")).resolve() \
        if meta.exists() else False


def _scene_dict(params, env_path: Path, mdir: Path, summary: dict, vs: list, data,
                cfg: RelightConfig, kind: str, indirect: bool) -> dict:
    """The surfels, the ``octenvmap`` emitter, the ``sop_pbr`` integrator (step 2's probe and
    trace settings) and one RGBA sensor per view."""
    emitter = {"type": "octenvmap", "filename": str(env_path), "scale": float(cfg.envmap_scale)}
    if cfg.envmap_res:
        emitter["resolution"] = int(cfg.envmap_res)
    integ = {"type": "sop_pbr", "visibility": kind, "rays": cfg.rays, "sampling": cfg.sampling,
             "indirect": indirect, "hide_emitters": True,
             "probe_k": summary["config"]["probe_k"], "trace_hits": summary["config"]["trace_hits"],
             "trace_offset": summary["config"]["trace_offset"] * object_size(params)}
    if kind == "sops":
        integ["probes"] = str(mdir / "probes.npz")
    scene_d = {"type": "scene", "surfels": SurfelShapeBase.from_params(params, id="surfels"),
               "env": emitter, "integrator": integ}
    for i, v in enumerate(vs):
        sd = v.camera.sensor_dict(**data.clip_planes())
        scene_d[f"sensor_{i:03d}"] = {**sd, "film": {**sd["film"], "pixel_format": "rgba"}}
    return scene_d


@dataclass
class _Truth:
    """Where the dataset keeps the ground truth of the rendered split."""
    base: Path                      # the dataset folder
    full_res: bool                  # the run is at full resolution (scores are comparable)
    relit_dir: Path                 # <split>_relight/<map stem>/ (make-dataset object)
    frames: dict                    # {file name: frame of transforms_<split>.json}


def _relight_view(scene, i: int, v, out: Path, bg: float, truth: _Truth) -> dict:
    """Render view ``i``, write its PNG and EXR layers; its scores against the ground truth."""
    with dr.suspend_grad():
        rgba = mi.render(scene, sensor=i, seed=7)
        img = np.asarray(display_composite(rgba, bg))
        pts, geo = scene.integrator().shading_points(scene, i)
    name = v.name.replace('/', '_')
    write_png8(out / f"{name}.png", img)
    exr.write_layers(out / f"{name}.exr",
                     material_layers(rgba, pts, geo, scene.sensors()[i]), MATERIAL_ATTRS)
    rec = {"view": v.name}
    stem = Path(v.name).name
    gt_p = truth.relit_dir / f"{stem}.exr"
    if truth.full_res and gt_p.exists():
        rec.update(_relit_scores(rgba, img, gt_p, bg))
    fr = truth.frames.get(stem)
    if fr is not None and truth.full_res:
        rec.update(_gbuffer_scores(fr, truth.base, pts, geo))
    return rec


def _relit_scores(rgba, img: np.ndarray, gt_p: Path, bg: float) -> dict:
    """Relighting PSNR/SSIM (display sRGB over the background) and the PSNR after the
    per-channel scale alignment s_c = median(gt_c / ours_c) of the linear straight colour
    over covered pixels (the light's and albedo's scale ambiguity)."""
    rec = {}
    gt = exr.read_image(gt_p).astype(np.float64)             # premultiplied linear
    a = gt[..., 3:4] if gt.shape[-1] > 3 else np.ones_like(gt[..., :1])
    straight = gt[..., :3] / np.maximum(a, 1e-6)
    gt_disp = a * _display(straight) + (1 - a) * bg
    rec["relight_psnr"] = M.psnr(np.clip(img, 0, 1), gt_disp)
    rec["relight_ssim"] = M.ssim(np.clip(img, 0, 1), gt_disp)
    lin = np.asarray(rgba, np.float64)
    Wp = lin[..., 3:4]
    ours = lin[..., :3] / np.maximum(Wp, 1e-6)
    cov = (a[..., 0] > 0.99) & (Wp[..., 0] > 0.99) & (ours.min(-1) > 1e-6)
    if cov.sum() >= 10:
        sc = np.array([np.median(straight[..., c][cov] / ours[..., c][cov]) for c in range(3)])
        aligned = Wp * _display(ours * sc) + (1 - Wp) * bg
        rec["relight_psnr_aligned"] = M.psnr(aligned, gt_disp)
    return rec


def _gbuffer_scores(fr: dict, base: Path, pts, geo) -> dict:
    """Albedo PSNR after :func:`align_albedo` and the normal MAE (degrees) against the
    frame's G-buffer ground truth, where the dataset has it."""
    rec = {}
    W = geo["W_np"]
    if "albedo_path" in fr and (base / fr["albedo_path"]).exists():
        ga = exr.read_image(base / fr["albedo_path"]).astype(np.float64)
        mask = (ga[..., 3] > 0.99) & (W > 0.5)
        pa = np.zeros_like(ga[..., :3]).reshape(-1, 3)
        pa[geo["pix_np"]] = np.asarray(pts.albedo).T
        pa = pa.reshape(ga.shape[:2] + (3,))
        al, s = align_albedo(pa, ga[..., :3], mask)
        m3 = mask[..., None]
        rec["albedo_psnr"] = M.psnr(_display(al) * m3, _display(ga[..., :3]) * m3)
        if (mask & (pa.min(-1) > 1e-4)).sum() >= 10:      # align_albedo's own condition
            rec.update({f"albedo_ratio_{c}": float(1.0 / s[i]) for i, c in enumerate("rgb")})
    if "normal_path" in fr and (base / fr["normal_path"]).exists():
        gn = exr.read_image(base / fr["normal_path"]).astype(np.float64)
        mask = (gn[..., 3] > 0.99) & (W > 0.5) if gn.shape[-1] > 3 else (W > 0.5)
        pn = np.zeros((W.size, 3))
        pn[geo["pix_np"]] = np.asarray(geo["n"]).T
        rec["normal_mae_deg"] = M.normal_mae_deg(pn.reshape(W.shape + (3,)),
                                                 gn[..., :3], mask.astype(np.float32))
    return rec
