"""Render a finished step-1 run on its test (or train) views and write metrics.

Per view ``render_<views>/<i>.exr`` holds the G-buffer (:func:`gbuffer_layers`) beside the
display PNGs."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np
from tqdm import tqdm

from comgs_dr.core import exr, runlog
from comgs_dr.core.cameras import camera_rays
from comgs_dr.core.colorspace import srgb_decode
from comgs_dr.core.hostarray import to_jit
from comgs_dr.data.images import write_png8
from comgs_dr.data.nerf import split_frames
from comgs_dr.emitters.octenvmap import emitter_class
from comgs_dr.eval import metrics as M
from comgs_dr.surfels import load_ply
from comgs_dr.surfels.scene import gbuffer_scene
from comgs_dr.train import background as bgenv
from comgs_dr.train import checkpoint as ck
from comgs_dr.train.run import load_run_dataset, read_run_info


VIEWS = ("test", "train")


@dataclass
class RenderConfig:
    """Settings of ``comgs render`` (:func:`render_run`).

    views: the split rendered and scored, ``test`` (default) or ``train``; max_hits: surfels
    blended along each ray at most (default 32).
    """
    views: str = "test"
    max_hits: int = 32

    def __post_init__(self):
        if self.views not in VIEWS:
            raise ValueError(f"RenderConfig.views must be test or train, got {self.views!r}")
        if self.max_hits < 1:
            raise ValueError(f"RenderConfig.max_hits must be >= 1, got {self.max_hits}")


def _gt_geometry(data_dir: Path, split: str) -> list:
    """Per-view (normal, depth) ground-truth EXR paths written by `comgs make-dataset`, if any."""
    return [(data_dir / fr["normal_path"] if "normal_path" in fr else None,
             data_dir / fr["depth_path"] if "depth_path" in fr else None)
            for fr in split_frames(data_dir, split)]


def gbuffer_layers(b: dict, background: float) -> dict:
    """EXR layers of a ``surfel_gbuffer`` render ``b`` ({target: [H, W, c]}): '' = linear
    RGB premultiplied by the coverage weight + A = weight (the run's display-sRGB colour,
    background removed, decoded as ``colorspace.unpremultiplied_to_linear``), 'depth' = ray
    distance, 'normal' = unit world normal (both 0 where uncovered)."""
    w = b["weight"].astype(np.float64)                                     # [H, W, 1]
    cov = w > 1e-4
    straight = (b["color"] - (1.0 - w) * background) / np.maximum(w, 1e-4)   # [H, W, 3]
    rgb = np.where(cov, w * srgb_decode(np.maximum(straight, 0.0)), 0.0)
    n = b["normal"].astype(np.float64)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(cov & (norm > 1e-8), n / np.maximum(norm, 1e-8), 0.0)
    return {"": np.concatenate([rgb, w], -1), "depth": np.where(cov, b["depth_unbiased"], 0.0),
            "normal": n}


GBUFFER_ATTRS = {"colour": "linear sRGB (Rec. 709 primaries), premultiplied by A = coverage",
                 "depth": "ray distance from the near-clip origin, 0 where uncovered",
                 "normal": "unit world-space normal, 0 where uncovered"}


def _sky_pixels(scene, i: int) -> np.ndarray:
    """[H, W, 3] the scene's environment along the pixel-centre rays of sensor ``i``."""
    sensor = scene.sensors()[i]
    dirs, _ = camera_rays(sensor)
    d = np.asarray(dirs, np.float32)
    e = scene.environment().eval_world(to_jit(mi.Vector3f, d.reshape(-1, 3).T))
    return np.asarray(e).T.reshape(d.shape).astype(np.float64)


def render_run(run_dir, views: str = "test", progress: bool = True, max_hits: int = 32) -> dict:
    """Render ``views`` ('test' or 'train'); write images and ``metrics_<views>.json``."""
    run_dir = Path(run_dir)
    info = read_run_info(run_dir)
    ply = run_dir / "point_cloud.ply"
    if not ply.exists():
        raise FileNotFoundError(f"{ply} not found: the run has not finished (resume it with `comgs reconstruct`)")
    data = load_run_dataset(run_dir, info)
    vs = data.test if views == "test" else data.train
    if not vs:
        raise ValueError(f"the dataset at {info['data']} has no {views} views")
    params = load_ply(str(ply))
    bg = 1.0 if data.white_background else 0.0
    sky = bgenv.load(run_dir)                 # step 1's learned sky (``--background env``)
    extra = {} if sky is None else dict(environment=emitter_class().from_radiance(sky[0]),
                                        env_background=True)
    scene = gbuffer_scene({"surfels": params}, [v.camera.sensor_dict(**data.clip_planes()) for v in vs], max_hits=max_hits,
                          background=bg, **extra)
    integ = scene.integrator()
    gt_geo = _gt_geometry(Path(info["data"]), views) if info["resolution_scale"] == 1 else []
    out_dir = run_dir / f"render_{views}"
    out_dir.mkdir(exist_ok=True)
    per_view = []
    for i in tqdm(range(len(vs)), desc=f"render {views}", unit="view", disable=not progress):
        v = vs[i]
        b = {k: np.asarray(t) for k, t in integ.split(mi.render(scene, sensor=i)).items()}
        c = np.clip(b["color"], 0, 1)
        write_png8(out_dir / f"{i:03d}_color.png", c)
        n_vis = (0.5 * b["normal"] + 0.5 * b["weight"]).clip(0, 1)
        write_png8(out_dir / f"{i:03d}_normal.png", n_vis)
        behind = bg if sky is None else _sky_pixels(scene, i)       # what T_final shows
        exr.write_layers(out_dir / f"{i:03d}.exr", gbuffer_layers(b, behind), GBUFFER_ATTRS)
        rec = {"view": v.name, "psnr": M.psnr(c, v.image), "ssim": M.ssim(c, v.image)}
        if i < len(gt_geo):
            npath, dpath = gt_geo[i]
            mask = v.mask if v.mask is not None else (b["weight"][..., 0] > 0.5).astype(np.float32)
            mask = ((mask > 0.99) & (b["weight"][..., 0] > 0.5)).astype(np.float32)
            if npath is not None and npath.exists():
                n_gt = exr.read_image(npath)[..., :3]
                rec["normal_mae_deg"] = M.normal_mae_deg(b["normal"], n_gt, mask)
            if dpath is not None and dpath.exists():
                d_gt = exr.read_image(dpath)[..., 0]
                rec.update(M.depth_errors(b["depth_unbiased"][..., 0], d_gt, mask))
        per_view.append(rec)
    keys = [k for k in per_view[0] if k != "view"]
    summary = {k: float(np.nanmean([r[k] for r in per_view if k in r])) for k in keys}
    result = {**summary, "views": len(vs), "surfels": params.count, "per_view": per_view}
    ck.atomic_write_text(run_dir / f"metrics_{views}.json", json.dumps(runlog.json_safe(result), indent=1,
                                                                     allow_nan=False))
    return result
