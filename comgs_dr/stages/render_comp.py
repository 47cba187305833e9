"""``comgs render-comp``: render a composition folder along NeRF cameras, the test views of a
captured dataset (COLMAP, LLFF, NeRF-synthetic folder), or a camera path around the placed
objects (``path``: orbit, spiral or a transforms.json; ``data.camera_path``), each camera
with its own pinhole intrinsics (fx, fy, cx, cy; ``data.comp_folder``).

Variants (the paper's composition table): ``sop`` (shadows from the cached probes),
``trace`` (occlusion traced per frame), ``noshadow`` (objects relit, no shadows on the
scene), ``paste`` (the objects' step-1 radiance depth-composited, no relighting, no
shadows). Writes ``COMP_DIR/renders/<variant>/<basename>.png`` (8-bit sRGB) and, with
ground truth (``GT_DIR/<basename>.png``), ``COMP_DIR/metrics_<variant>.json``: mean
``psnr``/``ssim``, ``frame_seconds`` (median over frames after the first, which includes
kernel compilation; ``first_frame_seconds`` apart) and a per-frame list. Where the ground
truth is a composition dataset's (``GT_DIR/../empty/<basename>.exr``, the scene without the
objects, and ``GT_DIR/../mask/<basename>.png``, their pixels), ``region`` adds what a user
looks at (``eval.comp_region``): PSNR in the object+shadow region, the shadow's darkness
against the truth's and the object's mean colour per channel against the truth's. Path
frames (``renders/<variant>/path_0000.png`` …) have no ground truth: no metrics, and the
summary (also written to ``COMP_DIR/path_<variant>.json``) says so; ``video`` also writes
them as an mp4 (imageio-ffmpeg).

:func:`render_comp` runs the phases in order: check the settings
(:meth:`RenderCompConfig.validate`), the cameras and their ground truth, load the scene,
render each frame (:func:`_render_frame`), summarise. Each frame is written through a
temporary file and a rename: a killed render leaves no partial PNG (its temporary is removed
when that frame is next rendered). ``frame_indices``, ``done`` and ``on_frame`` split one
render over processes (``comgs_dr.batch``): each renders a subset of the frames, the same
bytes as the whole run, and a last call summarises.
"""
from __future__ import annotations

import io
import json
import logging
import os
import secrets
import time
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from PIL import Image
from tqdm.auto import tqdm

from comgs_dr.core import runlog
from comgs_dr.core.colorspace import srgb_encode
from comgs_dr.data import camera_path, comp_folder
from comgs_dr.data.images import read_image, to_u8
from comgs_dr.integrators.comgs_composite import is_file_property
from comgs_dr.eval import comp_region
from comgs_dr.eval.metrics import psnr, ssim
from comgs_dr.surfels.edit import parse_material_spec
from comgs_dr.train.checkpoint import atomic_write_text, remove_stale_temporaries

VARIANTS = ("sop", "trace", "noshadow", "paste")
MAX_SIDE = 16384        # px a side; and W·H ≤ (MAX_SIDE/2)²: the per-hit buffers (W·H·max_hits
                        # entries) must stay below Dr.Jit's 2³² array limit
log = logging.getLogger(__name__)


@dataclass
class RenderCompConfig:
    """Settings of :func:`render_comp`.

    variant: "sop" (default: shadows from the cached probes), "trace" (occlusion traced per
        frame), "noshadow" or "paste" (see the module docstring).
    materials: {object name: material spec} overrides, not with "paste"; a spec as
        ``surfels.edit.parse_material_spec`` reads it: ``albedo=R,G,B`` (linear, in
        [0, 1]) or ``scale=S[,S,S]`` (multiplies the albedo), ``roughness=X``,
        ``metallic=Y``. Example: ``{"chair": "albedo=0.8,0.1,0.1,roughness=0.3"}``.
    res: image size in pixels, ``W`` (a W × W image) or ``(W, H)`` (None: the ground
        truth's, else the camera file's); at most ``MAX_SIDE`` a side and (MAX_SIDE/2)²
        pixels.
    rays: S_r, the integrator's rays per pixel for shading and for shadows (None: its
        default, 256).
    seed: sampler seed of the first frame; frame i renders with seed + i (default 0).
    path: render a camera path instead of capture views: "orbit" (a circle around the
        placed objects at the capture cameras' mean distance and elevation), "spiral" (the
        orbit with its height and distance swinging) or a NeRF transforms.json of cameras
        (``data.camera_path``); frames ``path_0000`` … with the intrinsics of the first
        capture camera (or ``res``); no ground truth, no metrics.
    frames: N, the number of path frames (None: 60 for orbit/spiral, a file's own count).
    video: also write the frames as this mp4 (H.264 via imageio-ffmpeg); its path goes in
        the summary.
    fps: frames per second of the video (default 24).
    """
    variant: str = "sop"
    materials: dict | None = None
    res: int | tuple | None = None
    rays: int | None = None
    seed: int = 0
    path: str | None = None
    frames: int | None = None
    video: str | None = None
    fps: float = 24.0

    def validate(self) -> None:
        """ValueError naming the first setting no render can use."""
        if self.variant not in VARIANTS:
            raise ValueError(f"render-comp: variant must be one of {', '.join(VARIANTS)}, "
                             f"got {self.variant!r}")
        if self.materials and self.variant == "paste":
            raise ValueError("render-comp: material overrides do not apply to variant 'paste' "
                             "(it shows the objects' captured radiance); use sop, trace or "
                             "noshadow")
        for spec in (self.materials or {}).values():
            parse_material_spec(spec)            # a clear error before anything is loaded
        res = self.res
        sizes = [] if res is None else [res] if isinstance(res, int) else list(res)
        if len(sizes) > 2 or any(isinstance(v, bool) or not isinstance(v, (int, np.integer))
                                 or v < 1 for v in sizes):
            raise ValueError(f"render-comp: res must be W or (W, H) with positive integers, "
                             f"got {res!r}")
        if any(v > MAX_SIDE for v in sizes):
            raise ValueError(f"render-comp: res {res!r} is beyond {MAX_SIDE} px a side")
        rays = self.rays
        if rays is not None and (isinstance(rays, bool) or int(rays) != rays or rays < 1):
            raise ValueError(f"render-comp: rays must be an integer >= 1, got {rays!r}")
        n = self.frames
        if n is not None and (isinstance(n, bool) or not isinstance(n, (int, np.integer))
                              or not 1 <= n <= camera_path.MAX_FRAMES):
            raise ValueError(f"render-comp: frames must be an integer in [1, "
                             f"{camera_path.MAX_FRAMES}], got {n!r}")
        if n is not None and self.path is None:
            raise ValueError("render-comp: frames is the length of a camera path: give path "
                             "(orbit, spiral or a transforms.json) too")
        if self.path is not None and str(self.path) not in camera_path.SHAPES and \
                Path(str(self.path)).suffix.lower() != ".json":
            raise ValueError(f"render-comp: path must be orbit, spiral or a transforms .json "
                             f"file, got {self.path!r}")
        if self.path is not None and str(self.path) not in camera_path.SHAPES and \
                not Path(str(self.path)).is_file():
            raise FileNotFoundError(f"render-comp: camera path file not found: {self.path}")
        if self.video is not None and Path(str(self.video)).suffix.lower() != ".mp4":
            raise ValueError(f"render-comp: video must be an .mp4 file, got {self.video!r}")
        fps = self.fps
        if isinstance(fps, bool) or not isinstance(fps, (int, float, np.number)) \
                or not (np.isfinite(fps) and 0 < fps <= 240):
            raise ValueError(f"render-comp: fps must be in (0, 240], got {fps!r}")


def load_comp_scene(comp_dir, variant: str = "sop", materials: dict | None = None,
                    sensors=(), **integrator_extra) -> mi.Scene:
    """The composition as a Mitsuba scene (``comgs_composite`` + surfels shapes)."""
    m = comp_folder.read_manifest(comp_dir)
    props = comp_folder.integrator_props(comp_dir, m, variant, materials, **integrator_extra)
    for k, v in props.items():      # here: mi.load_dict hides a plugin's error in its text
        if is_file_property(k, v) and not Path(v).is_file():
            raise FileNotFoundError(f"{comp_dir}: the composition's {k} file is missing: {v}")
    d = {"type": "scene", "integrator": props, **comp_folder.shape_dicts(m)}
    for i, s in enumerate(sensors):
        d[f"sensor_{i:03d}"] = s
    return mi.load_dict(d)


def render_comp(comp_dir, cameras=None, variant: str = "sop", gt_dir=None,
                materials: dict | None = None, res=None, rays: int | None = None,
                seed: int = 0, progress: bool = True, path=None, frames: int | None = None,
                video=None, fps: float = 24.0, frame_indices=None, done: dict | None = None,
                on_frame=None) -> dict:
    """Render every camera of ``cameras`` (a NeRF ``transforms*.json``, or a dataset
    folder / ``poses_bounds.npy``: its test views, ``comp_folder.camera_source``), or with
    ``path`` the frames of a camera path placed by those cameras (None: the scene run's
    dataset, as step 1 loads it); returns the metrics dict (written to
    ``metrics_<variant>.json`` when ``gt_dir`` is given). ``variant``, ``materials``,
    ``res``, ``rays``, ``seed``, ``path``, ``frames``, ``video``, ``fps``: see
    :class:`RenderCompConfig`.

    Sharding (``comgs_dr.batch``): ``frame_indices`` (a list, or a slice such as
    ``slice(k, None, n)``) renders only those frames (frame i still with ``seed + i``) and
    returns {"per_frame": their records, ...} without writing the metrics, path summary,
    video or ``render_<variant>.metrics.jsonl``; ``done``
    ({frame name: its record}) skips the frames whose PNG is already there and takes their
    records as given (the scene is not loaded when nothing is left to render);
    ``on_frame(i, record)`` is called once frame i's PNG is in place."""
    RenderCompConfig(variant, materials, res, rays, seed, path, frames, video, fps).validate()
    comp_dir = Path(comp_dir)
    manifest = comp_folder.read_manifest(comp_dir)
    if path is None:
        if cameras is None:
            raise ValueError("render-comp: give cameras (a transforms.json or a dataset "
                             "folder) or a camera path")
        cams = comp_folder.camera_source(cameras, manifest.get("world_from_source"), res)
    else:
        if gt_dir is not None:
            raise ValueError("render-comp: path frames have no ground truth: leave gt_dir "
                             "out with path")
        cams = _path_cameras(comp_dir, manifest, cameras, path, frames, res)
    gts = _ground_truth(gt_dir, cams, res) if gt_dir is not None else {}
    if gts:
        cams = [comp_folder.sized(c, *gts[c["name"]].shape[1::-1]) for c in cams]
    _check_frame_sizes(cams)
    regions = _region_truth(gt_dir, cams) if gt_dir is not None else {}
    extra = {"rays": int(rays), "shadow_rays": int(rays)} if rays else {}
    clip = comp_folder.clip_for(manifest, cams)        # scaled to the composition

    def scene():
        return load_comp_scene(comp_dir, variant, materials,
                               [comp_folder.sensor_dict(cams[0], clip=clip)], **extra)
    out_dir = _render_folder(comp_dir, variant, cams, gt_dir)
    recs = _render_frames(scene, cams, comp_dir, out_dir, variant, gts, regions, seed,
                          progress, clip, frame_indices, done or {}, on_frame)
    if frame_indices is not None:                # a shard: the last call summarises
        return {"variant": variant, "frames": len(recs), "renders": str(out_dir),
                "per_frame": recs}
    summary = _summarise(recs, cams, comp_dir, cameras, variant, out_dir, gts, regions)
    if path is not None:
        summary["path"] = str(path)
        summary["metrics"] = "skipped: path frames have no ground truth"
    if video is not None:
        summary["video"] = str(write_video(video, [out_dir / f"{c['name']}.png" for c in cams],
                                           fps))
        summary["video_bytes"] = Path(video).stat().st_size
    if path is not None:                     # no metrics file: the run's summary instead
        atomic_write_text(comp_dir / f"path_{variant}.json",
                          json.dumps(runlog.json_safe(summary), indent=1, allow_nan=False))
    return summary


def _path_cameras(comp_dir: Path, manifest: dict, cameras, path, frames, res) -> list[dict]:
    """The frames of a camera path (``data.camera_path``), placed by the capture cameras:
    ``cameras`` when given, else the scene run's dataset views (test, else train)."""
    wfs = manifest.get("world_from_source")
    if cameras is not None:
        capture = comp_folder.camera_source(cameras, wfs, None)
    else:
        from comgs_dr.train.run import load_run_dataset, read_run_info
        run = manifest["scene"].get("run")
        if not run:
            raise ValueError(f"{comp_dir / comp_folder.MANIFEST}: no scene run recorded: give "
                             f"cameras to place the path by")
        data = load_run_dataset(Path(run), read_run_info(Path(run)), pixels=False)
        capture = [comp_folder.camera(v.name, c.to_world, c.width, c.height, c.fx,
                                      c.fx * c.fy_over_fx, c.cx, c.cy)
                   for v in (data.test or data.train) for c in (v.camera,)]
    return camera_path.path_cameras(path, frames, capture, camera_path.objects_centre(manifest),
                                    res, wfs)


def write_video(video, pngs: list, fps: float = 24.0) -> Path:
    """``video`` (mp4, H.264 yuv420p, via imageio-ffmpeg) of the PNG frames ``pngs``; an
    odd width or height is padded by one edge pixel (yuv420p needs even sizes)."""
    import imageio.v2 as imageio
    out = Path(video)
    out.parent.mkdir(parents=True, exist_ok=True)
    with imageio.get_writer(str(out), fps=float(fps), codec="libx264", quality=8,
                            macro_block_size=1, pixelformat="yuv420p",
                            ffmpeg_log_level="error") as w:
        for p in pngs:
            img = np.asarray(read_image(p))[..., :3]
            img = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
            h, wd = img.shape[:2]
            img = np.pad(img, ((0, h % 2), (0, wd % 2), (0, 0)), mode="edge")
            w.append_data(img)
    return out


# ---------------------------------------------------------------------------------------
# Cameras and ground truth

def _ground_truth(gt_dir, cams: list, res) -> dict:
    """{frame: ground truth [H, W, 3]} of every camera; without ``res`` each camera takes
    its ground truth's size (``render_comp`` resizes them), with it the sizes must agree."""
    missing = [c["name"] for c in cams if not (Path(gt_dir) / f"{c['name']}.png").is_file()]
    if missing:
        raise FileNotFoundError(f"render-comp: no ground truth for {len(missing)} of "
                                f"{len(cams)} frames in {gt_dir} (e.g. {missing[0]}.png)")
    gts = {}
    for c in cams:
        gts[c["name"]] = read_image(Path(gt_dir) / f"{c['name']}.png")[..., :3]
        gh, gw = gts[c["name"]].shape[:2]
        if res is not None and (c["width"], c["height"]) != (gw, gh):
            raise ValueError(f"render-comp: res {c['width']}×{c['height']} is not the ground "
                             f"truth's size ({c['name']}.png is {gw}×{gh}): leave res out to "
                             f"render at the ground truth's size")
    return gts


def _check_frame_sizes(cams: list) -> None:
    """ValueError, before any frame renders, for frames of different sizes (a camera file
    with per-frame w/h: give res) or one beyond the (MAX_SIDE/2)² pixels of the hit
    buffer."""
    first = (cams[0]["width"], cams[0]["height"])
    other = next((c for c in cams if (c["width"], c["height"]) != first), None)
    if other is not None and None not in first:
        raise ValueError(f"render-comp: frame {other['name']} is {other['width']}×"
                         f"{other['height']}, the first frame {first[0]}×{first[1]}: one size "
                         f"per run (give res to render every camera at one size)")
    for c in cams:
        if c["width"] is not None and c["width"] * c["height"] > MAX_SIDE * MAX_SIDE // 4:
            raise ValueError(f"render-comp: frame {c['name']} is {c['width']}×{c['height']} px, "
                             f"beyond the {MAX_SIDE // 2}² the hit buffer holds; give a "
                             f"smaller res")


def _region_truth(gt_dir, cams) -> dict:
    """{frame: (empty linear [H, W, 3], object mask [H, W])} where the composition dataset
    beside ``gt_dir`` has both for every frame; {} otherwise (region scores left out)."""
    from comgs_dr.core.exr import read_image as read_exr
    root = Path(gt_dir).parent
    paths = {c["name"]: (root / "empty" / f"{c['name']}.exr", root / "mask" / f"{c['name']}.png")
             for c in cams}
    if not all(e.is_file() and m.is_file() for e, m in paths.values()):
        return {}
    out = {}
    for name, (e, m) in paths.items():
        mask = read_image(m)
        out[name] = (read_exr(e)[..., :3], (mask[..., 0] if mask.ndim == 3 else mask) > 0.5)
    return out


# ---------------------------------------------------------------------------------------
# Rendering

def _render_folder(comp_dir: Path, variant: str, cams: list, gt_dir) -> Path:
    """``COMP_DIR/renders/<variant>/``, created; warns about what an earlier run left."""
    out_dir = comp_dir / "renders" / variant
    out_dir.mkdir(parents=True, exist_ok=True)
    names = {f"{c['name']}.png" for c in cams}
    stale = sorted(p.name for p in out_dir.glob("*.png") if p.name not in names)
    if stale:
        log.warning("render-comp: %s holds %d frame(s) not of these cameras (e.g. %s), from an "
                    "earlier run: they are left there", out_dir, len(stale), stale[0])
    if not gt_dir and (comp_dir / f"metrics_{variant}.json").is_file():
        log.warning("render-comp: %s is from an earlier run with ground truth (its 'cameras' "
                    "says which); without --gt-dir it is not rewritten",
                    comp_dir / f"metrics_{variant}.json")
    return out_dir


def _render_frames(load_scene, cams: list, comp_dir: Path, out_dir: Path, variant: str,
                   gts: dict, regions: dict, seed: int, progress: bool, clip: dict | None = None,
                   indices=None, done: dict | None = None, on_frame=None) -> list[dict]:
    """Render every camera (frame i with ``seed + i``, its own pose and intrinsics) into
    ``out_dir``, or those of ``indices`` (a list or a slice); per frame a record (name,
    seconds, scores), each also appended to ``render_<variant>.metrics.jsonl`` (not for
    ``indices``). A frame of ``done`` whose PNG is there keeps its record; ``load_scene()``
    is called at the first frame to render."""
    scene = sensor = params = perspective = None
    frames = []
    size = (cams[0]["width"], cams[0]["height"])
    stage, jsonl = f"render-comp {variant}", f"render_{variant}.{runlog.LOG_NAME}"
    if indices is None:                             # (render time, per-frame error) records
        runlog.rewrite(comp_dir, [], name=jsonl)
    todo = range(len(cams)) if indices is None else range(len(cams))[indices] \
        if isinstance(indices, slice) else [int(j) for j in indices]
    for i in tqdm(todo, desc=f"render-comp {variant}", unit="frame", disable=not progress):
        c = cams[i]
        if (c["width"], c["height"]) != size:
            raise ValueError(f"render-comp: frame {c['name']} is {c['width']}×{c['height']}, "
                             f"the first frame {size[0]}×{size[1]}: one size per camera file")
        rec = (done or {}).get(c["name"])
        if rec is None or not (out_dir / f"{c['name']}.png").is_file():
            if scene is None:
                scene = load_scene()
                sensor = scene.sensors()[0]
                params = mi.traverse(sensor)
                perspective = sensor.class_name() == "PerspectiveCamera"
            rec = _render_frame(scene, _frame_sensor(sensor, params, perspective, c, clip),
                                c["name"], seed + i, out_dir, gts, regions)
            if on_frame is not None:
                on_frame(i, rec)
        frames.append(rec)
        if indices is not None:
            continue
        runlog.append(comp_dir, runlog.record(stage, sum(f["seconds"] for f in frames),
                                              frame=i, **{k: v for k, v in rec.items()
                                                          if k in ("psnr", "ssim", "psnr_region")}),
                      name=jsonl)
    return frames


def _frame_sensor(sensor, params, perspective: bool, cam: dict, clip: dict | None):
    """The scene's sensor moved to ``cam`` (pose, field of view, principal point), or, for
    a camera with fx ≠ fy, a ``comgs_pinhole`` sensor of its own."""
    d = comp_folder.sensor_dict(cam, clip=clip)
    if not perspective or d["type"] != "perspective":
        return mi.load_dict(d)
    params["to_world"] = d["to_world"]
    params["x_fov"] = d["fov"]
    params["principal_point_offset_x"] = d["principal_point_offset_x"]
    params["principal_point_offset_y"] = d["principal_point_offset_y"]
    params.update()
    return sensor


def _render_frame(scene, sensor, name: str, seed: int, out_dir: Path, gts: dict,
                  regions: dict) -> dict:
    """Render one frame, write ``<name>.png`` and score the written 8-bit image against
    the ground truth (and its region) where there is one."""
    t = time.perf_counter()
    img = mi.render(scene, sensor=sensor, seed=seed)
    dr.eval(img)
    lin = np.asarray(img, np.float32)[..., :3]
    dt = time.perf_counter() - t
    if not np.all(np.isfinite(lin)):
        raise FloatingPointError(f"render-comp: frame {name} has non-finite pixels")
    disp = np.clip(srgb_encode(np.clip(lin, 0.0, None)), 0.0, 1.0)
    write_frame_png(out_dir / f"{name}.png", disp)
    rec = {"name": name, "seconds": dt}
    if name in gts:
        q = np.round(disp * 255.0) / 255.0          # score the written 8-bit image
        rec.update(psnr=psnr(q, gts[name]), ssim=ssim(q, gts[name]))
    if name in regions:
        rs = comp_region.frame_scores(q, gts[name], *regions[name])
        rec["region"] = rs
        if rs["region_pixels"]:
            rec["psnr_region"] = -10 * np.log10(max(rs["region_mse"], 1e-12))
    return rec


def write_frame_png(path: Path, disp: np.ndarray) -> None:
    """``disp`` (display values in [0, 1]) as an 8-bit PNG, the bytes ``write_png8``
    writes, through a temporary file and a rename: a killed process leaves no partial PNG,
    and what an earlier killed write left (``<name>.png.*.tmp``) is removed first."""
    remove_stale_temporaries(path)
    buf = io.BytesIO()
    Image.fromarray(to_u8(disp)).save(buf, format="PNG")
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:                               # (mode 0666 less the umask, as a plain write)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(buf.getvalue())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _summarise(frames: list, cams: list, comp_dir: Path, cameras, variant: str, out_dir: Path,
               gts: dict, regions: dict) -> dict:
    """The metrics dict of :func:`render_comp`; with ground truth also written to
    ``metrics_<variant>.json``."""
    times = [f["seconds"] for f in frames]
    summary = {"variant": variant, "cameras": None if cameras is None else str(cameras),
               "frames": len(frames),
               "resolution": [cams[0]["width"], cams[0]["height"]],
               "frame_seconds": float(np.median(times[1:] if len(times) > 1 else times)),
               "first_frame_seconds": times[0], "renders": str(out_dir), "per_frame": frames}
    if gts:
        summary["psnr"] = float(np.mean([f["psnr"] for f in frames]))
        summary["ssim"] = float(np.mean([f["ssim"] for f in frames]))
        if regions:
            summary["region"] = comp_region.summarise([f.pop("region") for f in frames])
        atomic_write_text(comp_dir / f"metrics_{variant}.json",
                          json.dumps(runlog.json_safe(summary), indent=1, allow_nan=False))
    return summary


def summary_line(summary: dict) -> str:
    """What ``comgs render-comp`` prints of a :func:`render_comp` summary."""
    s = summary
    line = (f"{s['frames']} frame(s) ({s['variant']}), first {s['first_frame_seconds']:.2f} s "
            f"(kernel compilation included)" + (f", then {s['frame_seconds']:.3f} s/frame "
                                                  f"(median)" if s["frames"] > 1 else ""))
    if "psnr" in s:
        line += f", PSNR {s['psnr']:.2f} dB, SSIM {s['ssim']:.4f}"
    if "path" in s:
        line += f", camera path {s['path']} (no ground truth: no metrics)"
    line += f"; renders in {s['renders']}"
    return line + (f"; video {s['video']} ({s['video_bytes'] / 1024:.0f} KiB)"
                   if "video" in s else "")
