"""Cut an object out of its own capture (``comgs cut``): no masks needed.

A user photographs an object standing on something (a table, a bed, the floor) and runs
step 1 on the whole capture. This stage finds the object in that run's surfels and writes
it as a run of its own. Phases (one function each, :func:`cut_object` runs them):

1. **load** — the run's ``point_cloud.ply``, its dataset's cameras (and SfM points).
2. **look-at point** — the least-squares point nearest every camera's optical axis; the
   *scene size* s is the cameras' median distance to it (the unit of every length below).
3. **fit plane** — RANSAC on the centres of the opaque surfels (or the SfM points) within
   ``plane_radius``·s of the look-at point: the dominant plane below it with the cameras
   above it, normal toward the cameras (``surfels.cut.fit_support_plane``).
4. **select** — the surfels standing on the plane nearest the look-at point, grown over a
   radius graph (``surfels.cut.grow_object``), or those inside ``--object-box``.
5. **measure** — the opacity-weighted share of kept surfels below the plane (should be ~0)
   and inside a thin slab above it, all and lying flat (floor / bed-sheet remnants).
6. **write** — ``OBJECT_RUN/``:

   ``point_cloud.ply``  the kept surfels in the *object frame*: the plane is z = 0, +z up
                        (toward the cameras), the origin under the centre of the object's
                        footprint, x along world +X projected on the plane; unit scale.
   ``cut.json``         ``object_from_world`` / ``world_from_object`` (4×4, row-major),
                        ``plane_from_world`` (the frame of ``--box-frame plane``),
                        the plane and look-at point in the run's world frame, the
                        selection, the measures, the config.
   ``run.json``, ``data/transforms_{train,test}.json``, ``data/points3d.ply``
                        the capture's cameras moved into the object frame (NeRF layout,
                        ``fl_x fl_y cx cy w h``), so ``comgs render``/``report``/
                        ``decompose`` read the object run like any step-1 run.
   ``masks/<image>.png``  with ``masks``: per image of the dataset, the share of the pixel
                        the kept surfels cover as seen in the whole reconstruction (the
                        rest occludes them), rendered at the run's resolution and scaled to
                        the photo's; and ``data/images/<image>.png`` the photos with that
                        alpha, so ``comgs reconstruct OBJECT_RUN/data`` is an object-only
                        step 1 (object preset: mask loss, visual-hull init).

Masks the dataset ships (``DATASET/masks/<image>.png`` or ``<stem>.<ext>``, as
photogrammetry captures do) are used as they are where present, and reported.
"""
from __future__ import annotations

import dataclasses
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np

from comgs_dr.core import runlog
from comgs_dr.data.images import IMAGE_EXTENSIONS, read_image, read_mask, write_png8
from comgs_dr.data.load import load_dataset
from comgs_dr.data.sfm_points import write_points_ply
from comgs_dr.data.types import MITSUBA_FROM_OPENGL, Camera
from comgs_dr.surfels import cut as C
from comgs_dr.surfels.io import load_ply, quat_to_matrix, save_ply
from comgs_dr.surfels.params import base_colour
from comgs_dr.surfels.params import SurfelParams
from comgs_dr.train.checkpoint import atomic_write_text
from comgs_dr.train.run import check_run_cameras, read_run_info, write_run_info

CutError = C.CutError
PLANE_POINTS = ("surfels", "sfm")
BOX_FRAMES = ("world", "plane")
CUT_FILE = "cut.json"


@dataclasses.dataclass
class CutConfig:
    """Settings of ``comgs cut``. Lengths are fractions of the *scene size* s, the cameras'
    median distance to their look-at point (a phone orbit at 50 cm: s = 0.5 m, so 0.01 is
    5 mm).

    plane_points: what the plane is fitted to, ``surfels`` (centres of surfels with opacity
        ≥ ``min_opacity``, weighted by opacity) or ``sfm`` (the dataset's SfM points).
    plane_tolerance: RANSAC inlier distance (× s).
    plane_radius: only points this close to the look-at point vote for the plane (× s).
    plane_iterations: RANSAC hypotheses (count).
    plane_max_tilt_deg: largest angle (degrees) between the plane normal and the cameras'
        mean up vector (ignored when the cameras' up vectors disagree).
    plane_min_inliers: least share of the voting points (weighted) on the plane (0–1).
    min_opacity: surfels fainter than this (opacity 0–1) neither vote nor link the object;
        they are attached to it afterwards when within ``grow_radius`` of a kept surfel.
    min_height: kept surfels are at least this high above the plane (× s).
    slab_height: top of the low slab (× s): surfels between ``min_height`` and this height
        are kept only under the object's footprint (the base), the rest is floor/sheet; the
        measures' slab too.
    grow_radius: surfels closer than this are linked (× s); at least ``grow_spacing`` ×
        the surfels' own spacing.
    grow_spacing: the link radius is at least this many times the median distance of the
        solid surfels near the look-at point to their 4th nearest neighbour (a sparse
        reconstruction stays linked); 0: ``grow_radius`` only.
    footprint: horizontal reach of the object's footprint for its base (× s).
    seed_distance: the object must have a surfel above the slab this close to the look-at
        point (× s).
    min_component: linked groups of fewer surfels (count) are floaters, passed over.
    object_box: (xmin, ymin, zmin, xmax, ymax, zmax): keep the surfels inside this box
        instead of growing (scene units, in ``box_frame``).
    box_frame: ``world`` (the run's frame, as its ``point_cloud.ply``) or ``plane`` (z up
        from the plane, origin at the foot of the look-at point, x along world +X projected
        on the plane: the frame ``comgs cut`` prints).
    masks: also write alpha masks and an RGBA object dataset (see the module docstring).
    seed: RANSAC random seed.
    """
    plane_points: str = "surfels"
    plane_tolerance: float = 0.01
    plane_radius: float = 1.0
    plane_iterations: int = 400
    plane_max_tilt_deg: float = 50.0
    plane_min_inliers: float = 0.05
    min_opacity: float = 0.1
    min_height: float = 0.002
    slab_height: float = 0.03
    grow_radius: float = 0.015
    grow_spacing: float = 2.0
    footprint: float = 0.005
    seed_distance: float = 0.3
    min_component: int = 30
    object_box: tuple[float, ...] | None = None
    box_frame: str = "world"
    masks: bool = False
    seed: int = 0

    def __post_init__(self):
        if self.plane_points not in PLANE_POINTS:
            raise ValueError(f"CutConfig.plane_points must be one of {PLANE_POINTS}, got "
                             f"{self.plane_points!r}")
        if self.box_frame not in BOX_FRAMES:
            raise ValueError(f"CutConfig.box_frame must be one of {BOX_FRAMES}, got "
                             f"{self.box_frame!r}")
        positive = ("plane_tolerance", "plane_radius", "slab_height", "grow_radius",
                    "footprint", "seed_distance")
        for name in positive:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"CutConfig.{name} must be a finite number > 0, got {v!r}")
        if not (math.isfinite(self.min_height) and 0 <= self.min_height < self.slab_height):
            raise ValueError(f"CutConfig.min_height must be in [0, slab_height = "
                             f"{self.slab_height}), got {self.min_height!r}")
        for name in ("plane_min_inliers", "min_opacity"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"CutConfig.{name} must be in [0, 1), got {getattr(self, name)!r}")
        if not 0.0 < self.plane_max_tilt_deg <= 90.0:
            raise ValueError(f"CutConfig.plane_max_tilt_deg must be in (0, 90], got "
                             f"{self.plane_max_tilt_deg!r}")
        if not (math.isfinite(self.grow_spacing) and self.grow_spacing >= 0):
            raise ValueError(f"CutConfig.grow_spacing must be >= 0, got {self.grow_spacing!r}")
        if self.plane_iterations < 1 or self.min_component < 1:
            raise ValueError("CutConfig.plane_iterations and min_component must be >= 1")
        if self.object_box is not None:
            self.object_box = _check_box(self.object_box)


def _check_box(box) -> tuple[float, ...]:
    b = tuple(float(v) for v in box)
    if len(b) != 6 or not all(math.isfinite(v) for v in b):
        raise ValueError(f"CutConfig.object_box needs 6 finite numbers (xmin ymin zmin xmax "
                         f"ymax zmax), got {box!r}")
    if any(b[i] >= b[i + 3] for i in range(3)):
        raise ValueError(f"CutConfig.object_box: each min must be below its max, got "
                         f"min {b[:3]} max {b[3:]}")
    return b


# ----------------------------------------------------------------------------- phase 1: load

@dataclasses.dataclass
class Source:
    """A step-1 run and its dataset's cameras (full resolution, no pixels)."""
    run_dir: Path
    ply: Path
    data_dir: Path
    info: dict                      # the run's run.json
    params: SurfelParams
    color_space: str
    means: np.ndarray               # [N, 3] float64
    opacity: np.ndarray             # [N] in (0, 1)
    normals: np.ndarray             # [N, 3] unit
    data: object                    # SceneData (cameras only)

    @property
    def views(self) -> list:
        return self.data.train + self.data.test

    @property
    def centres(self) -> np.ndarray:
        return np.array([v.camera.center for v in self.views])


def load_source(run_dir, data_dir=None) -> Source:
    """Phase 1: the run's surfels, and the cameras of ``data_dir`` (default: the run's)."""
    run_dir = Path(run_dir)
    info = read_run_info(run_dir)
    ply = run_dir / "point_cloud.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"{ply} not found: the run has not finished (resume it with "
                                "`comgs reconstruct`)")
    params, meta = load_ply(ply, return_meta=True)
    d = params.to_numpy()
    if data_dir is None:
        check_run_cameras(run_dir, info)
    data_dir = Path(data_dir if data_dir is not None else info["data"])
    data = load_dataset(data_dir, pixels=False)
    normals = quat_to_matrix(d["quats"])[:, :, 2]
    opacity = 1.0 / (1.0 + np.exp(-d["opacity_logit"].astype(np.float64)))
    return Source(run_dir, ply, data_dir, info, params, meta.color_space,
                  d["means"].astype(np.float64), opacity, normals, data)


# ----------------------------------------------------------------------------- phase 2: look-at

def find_look_at(src: Source) -> dict:
    """Phase 2: {"point", "spread_deg", "scene_size"} from the cameras' optical axes."""
    axes = np.array([v.camera.to_world[:3, 2] for v in src.views])     # Mitsuba +Z forward
    solid = src.means[src.opacity >= 0.5]
    point, spread = C.look_at_point(src.centres, axes, solid)
    size = float(np.median(np.linalg.norm(src.centres - point, axis=1)))
    if not size > 0:
        raise CutError(f"{src.data_dir}: the cameras sit on their look-at point (scene size 0)")
    return {"point": point, "spread_deg": spread, "scene_size": size}


# ----------------------------------------------------------------------------- phase 3: plane

def fit_plane(src: Source, look: dict, cfg: CutConfig) -> C.Plane:
    """Phase 3: the support plane (``surfels.cut.fit_support_plane``)."""
    s = look["scene_size"]
    if cfg.plane_points == "sfm":
        if src.data.points is None or len(src.data.points) < 3:
            raise CutError(f"{src.data_dir}: plane_points=sfm but the dataset has no SfM "
                           "points (use --plane-points surfels)")
        pts = np.asarray(src.data.points, np.float64)
        w, where = np.ones(len(pts)), f"{src.data_dir} (SfM points)"
    else:
        solid = src.opacity >= cfg.min_opacity
        pts, w, where = src.means[solid], src.opacity[solid], str(src.ply)
    ups = [v.camera.to_world[:3, 1] for v in src.views]               # Mitsuba +Y up
    return C.fit_support_plane(
        pts, w, look["point"], src.centres, tolerance=cfg.plane_tolerance * s,
        radius=cfg.plane_radius * s, iterations=cfg.plane_iterations, up=C.mean_up(ups),
        max_tilt_deg=cfg.plane_max_tilt_deg, min_inlier_share=cfg.plane_min_inliers,
        seed=cfg.seed, where=where)


# ----------------------------------------------------------------------------- phase 4: select

def select(src: Source, look: dict, plane: C.Plane, cfg: CutConfig) -> dict:
    """Phase 4: {"keep": [N] bool, "method", ...}: grown from the look-at point, or the box."""
    s = look["scene_size"]
    heights = plane.height(src.means)
    to_plane = C.plane_frame(plane, look["point"])
    if cfg.object_box is not None:
        frame = to_plane if cfg.box_frame == "plane" else np.eye(4)
        p = src.means @ frame[:3, :3].T + frame[:3, 3]
        span = (np.percentile(p, 0.5, 0), np.percentile(p, 99.5, 0))
        keep = C.box_selection(p, cfg.object_box, str(src.ply), cfg.box_frame, span)
        return {"keep": keep, "method": "box", "box": list(cfg.object_box),
                "box_frame": cfg.box_frame}
    radius, spacing = C.link_radius(src.means, src.opacity, look["point"],
                                    radius=cfg.grow_radius * s, reach=cfg.seed_distance * s,
                                    min_opacity=cfg.min_opacity, spacing_factor=cfg.grow_spacing)
    sel = C.grow_object(
        src.means, src.opacity, heights, look["point"], radius=radius,
        seed_distance=cfg.seed_distance * s, min_height=cfg.min_height * s,
        slab=cfg.slab_height * s, footprint=cfg.footprint * s, min_opacity=cfg.min_opacity,
        min_component=cfg.min_component, to_plane=to_plane, where=str(src.ply))
    return {"keep": sel.keep, "method": "grow", "body": sel.body, "base": sel.base,
            "faint": sel.faint, "seed_distance": sel.seed_distance,
            "components": [{"surfels": n, "distance": d} for n, d in sel.components],
            "link_radius": radius, "spacing": spacing}


# ----------------------------------------------------------------------------- phase 5: measure

def measure(src: Source, plane: C.Plane, keep: np.ndarray, look: dict, cfg: CutConfig) -> dict:
    """Phase 5: the cut's cleanliness (``surfels.cut.cut_measures``) and its size."""
    m = C.cut_measures(plane.height(src.means), src.opacity, src.normals, plane.normal, keep,
                       cfg.slab_height * look["scene_size"])
    m["surfels"] = int(len(keep))
    f = C.plane_frame(plane, look["point"])
    q = src.means[keep] @ f[:3, :3].T + f[:3, 3]
    m["plane_frame_box"] = np.concatenate([np.percentile(q, 0.5, 0),
                                           np.percentile(q, 99.5, 0)]).tolist()
    return m


def object_frame(src: Source, plane: C.Plane, keep: np.ndarray, look: dict) -> np.ndarray:
    """[4, 4] world → object frame: the plane frame re-centred under the middle of the kept
    surfels' footprint (their 0.5–99.5 percentile box in the plane's x, y)."""
    p0 = C.plane_frame(plane, look["point"])
    q = src.means[keep] @ p0[:3, :3].T + p0[:3, 3]
    mid = 0.5 * (np.percentile(q[:, :2], 0.5, 0) + np.percentile(q[:, :2], 99.5, 0))
    origin = p0[:3, :3].T @ (np.array([mid[0], mid[1], 0.0]) - p0[:3, 3])
    return C.plane_frame(plane, origin)


# ----------------------------------------------------------------------------- phase 6: write

def transform_params(params: SurfelParams, keep: np.ndarray, m: np.ndarray) -> SurfelParams:
    """The kept surfels moved by the rigid world → object transform ``m`` [4, 4]."""
    from comgs_dr.core.similarity import Similarity
    from comgs_dr.surfels.transform import transform_surfels
    return transform_surfels(params.subset(keep), Similarity(1.0, m[:3, :3], m[:3, 3]))


def write_object_run(out: Path, src: Source, obj: SurfelParams, m: np.ndarray,
                     frames: dict) -> None:
    """``point_cloud.ply``, ``run.json`` and ``data/`` (cameras in the object frame);
    ``frames`` {split: [(view, file_path)]} (``file_path`` of each photo in ``data/``)."""
    out.mkdir(parents=True, exist_ok=True)
    save_ply(obj, out / "point_cloud.ply", color_space=src.color_space)
    data = out / "data"
    data.mkdir(exist_ok=True)
    for split, items in frames.items():
        if items:
            atomic_write_text(data / f"transforms_{split}.json", json.dumps(
                {"frames": [_frame(v, m, fp) for v, fp in items]}, indent=1))
    d = obj.to_numpy()
    rgb = np.clip(base_colour(d["sh"]), 0, 1) * 255 + 0.5
    write_points_ply(data / "points3d.ply", d["means"], rgb.astype(np.uint8))
    write_run_info(out, data, "object", src.info["resolution_scale"],
                   src.info["white_background"])


def _frame(view, m: np.ndarray, file_path: str) -> dict:
    cam = view.camera
    c2w = m @ cam.to_world @ MITSUBA_FROM_OPENGL                      # OpenGL camera-to-world
    return {"file_path": file_path, "transform_matrix": c2w.tolist(), "fl_x": cam.fx,
            "fl_y": cam.fx, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height}


def mask_name(view_name: str) -> str:
    """``masks/<this>``: the image's name with its image extension replaced by ``.png``."""
    p = Path(view_name)
    return (p.with_suffix("") if p.suffix.lower() in IMAGE_EXTENSIONS else p).as_posix() + ".png"


def given_masks(data_dir: Path, views: list) -> dict:
    """{view name: mask path} of the masks the dataset ships in ``masks/``: the image's
    name + ``.png`` (COLMAP), or its name or file name without the extension with any image
    extension."""
    folder = data_dir / "masks"
    if not folder.is_dir():
        return {}
    by_stem = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS:
            by_stem.setdefault(p.relative_to(folder).with_suffix("").as_posix(), p)
    out = {}
    for v in views:
        stem = Path(mask_name(v.name)).with_suffix("")
        p = folder / f"{v.name}.png"
        p = p if p.is_file() else by_stem.get(stem.as_posix(), by_stem.get(stem.name))
        if p is not None:
            out[v.name] = p
    return out


def render_masks(src: Source, keep: np.ndarray, views: list, progress: bool) -> dict:
    """{view name: [H, W] float32 in [0, 1]} at the photos' resolution: the composited
    weight of the kept surfels among all surfels (albedo target: kept 1, rest 0), rendered
    at the run's resolution scale and resized."""
    import mitsuba as mi
    from PIL import Image
    from tqdm import tqdm

    from comgs_dr.surfels.scene import gbuffer_scene
    k = int(src.info["resolution_scale"])
    d = src.params.to_numpy()
    d["albedo"] = np.repeat(keep.astype(np.float32)[:, None], 3, 1)
    marked = SurfelParams.from_numpy(**d)
    sensors = [_scaled(v.camera, k).sensor_dict(**src.data.clip_planes()) for v in views]
    scene = gbuffer_scene({"surfels": marked}, sensors, targets="albedo")
    integ = scene.integrator()
    out = {}
    for i, v in enumerate(tqdm(views, desc="masks", unit="view", disable=not progress)):
        a = np.asarray(integ.split(mi.render(scene, sensor=i))["albedo"])[..., 0]
        a = np.clip(a, 0.0, 1.0).astype(np.float32)
        w, h = v.camera.width, v.camera.height
        img = Image.fromarray(a).resize(((w // k) * k, (h // k) * k), Image.BILINEAR)
        full = np.zeros((h, w), np.float32)
        full[:img.size[1], :img.size[0]] = np.asarray(img)
        full[img.size[1]:, :] = full[img.size[1] - 1:img.size[1], :]
        full[:, img.size[0]:] = full[:, img.size[0] - 1:img.size[0]]
        out[v.name] = full
    return out


def _scaled(cam: Camera, k: int) -> Camera:
    """The camera of an image downscaled by ``k`` (as ``data.images.load_view`` makes it)."""
    if k == 1:
        return cam
    w, h = cam.width, cam.height
    return Camera.from_intrinsics(cam.to_world, w // k, h // k, cam.fx / k, cam.fx / k,
                                  cam.cx / k, cam.cy / k, where="cut")


def write_masks(out: Path, src: Source, keep: np.ndarray, progress: bool) -> tuple[dict, dict]:
    """``masks/`` and ``data/images/`` (RGBA photos) for every view; the dataset's own masks
    where it ships them, rendered ones elsewhere. Returns ({view name: data file path},
    report)."""
    views = src.views
    given = given_masks(src.data_dir, views)
    todo = [v for v in views if v.name not in given]
    rendered = render_masks(src, keep, todo, progress) if todo else {}
    paths, cover = {}, []
    for v in views:
        rel = mask_name(v.name)
        (out / "masks" / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / "data" / "images" / rel).parent.mkdir(parents=True, exist_ok=True)
        if v.name in given:
            shutil.copyfile(given[v.name], out / "masks" / rel)
            alpha = read_mask(given[v.name])
        else:
            alpha = rendered[v.name]
            write_png8(out / "masks" / rel, alpha)
        rgb = read_image(v.path)[..., :3]
        if alpha.shape != rgb.shape[:2]:
            raise CutError(f"{given.get(v.name, out / 'masks' / rel)}: mask is "
                           f"{alpha.shape[1]}x{alpha.shape[0]} but its image {v.path} is "
                           f"{rgb.shape[1]}x{rgb.shape[0]}")
        write_png8(out / "data" / "images" / rel, np.concatenate([rgb, alpha[..., None]], -1))
        paths[v.name] = f"images/{rel}"
        cover.append(float(alpha.mean()))
    return paths, {"given": len(given), "rendered": len(rendered),
                   "given_folder": str(src.data_dir / "masks") if given else None,
                   "mean_coverage": float(np.mean(cover)) if cover else 0.0}


# ----------------------------------------------------------------------------- the stage

def cut_object(run_dir, out_dir, cfg: CutConfig | None = None, data_dir=None,
               progress: bool = True) -> dict:
    """Cut the object out of step-1 run ``run_dir`` into ``out_dir`` (module docstring);
    returns the summary also written to ``out_dir/cut.json``. CutError (a ValueError naming
    the file) when no plane is found, nothing stands above it near the look-at point, or the
    box holds nothing."""
    cfg = cfg or CutConfig()
    out, t = Path(out_dir), {}
    clock = time.perf_counter()

    def lap(name):
        nonlocal clock
        now = time.perf_counter()
        t[name], clock = round(now - clock, 3), now

    src = load_source(run_dir, data_dir)
    lap("load")
    look = find_look_at(src)
    lap("look_at")
    plane = fit_plane(src, look, cfg)
    lap("plane")
    sel = select(src, look, plane, cfg)
    keep = sel.pop("keep")
    lap("select")
    meas = measure(src, plane, keep, look, cfg)
    m = object_frame(src, plane, keep, look)
    lap("measure")
    obj = transform_params(src.params, keep, m)
    out.mkdir(parents=True, exist_ok=True)
    masks, files = None, {v.name: str(Path(v.path).resolve()) for v in src.views}
    if cfg.masks:
        files, masks = write_masks(out, src, keep, progress)
        lap("masks")
    frames = {"train": [(v, files[v.name]) for v in src.data.train],
              "test": [(v, files[v.name]) for v in src.data.test]}
    write_object_run(out, src, obj, m, frames)
    summary = _summary(src, look, plane, sel, meas, m, masks, cfg, out)
    lap("write")
    summary["seconds"] = t
    atomic_write_text(out / CUT_FILE, json.dumps(runlog.json_safe(summary), indent=1,
                                                 allow_nan=False))
    return summary


def _summary(src, look, plane, sel, meas, m, masks, cfg, out) -> dict:
    given = given_masks(src.data_dir, src.views) if masks is None else {}
    return {
        "source": {"run": str(src.run_dir.resolve()), "point_cloud": str(src.ply.resolve()),
                   "data": str(src.data_dir.resolve()), "run_data": src.info["data"]},
        "object_run": str(out.resolve()),
        "object_from_world": m.tolist(), "world_from_object": np.linalg.inv(m).tolist(),
        "plane_from_world": C.plane_frame(plane, look["point"]).tolist(),
        "look_at": {"point": look["point"].tolist(), "axes_spread_deg": look["spread_deg"],
                    "scene_size": look["scene_size"]},
        "plane": {"normal": plane.normal.tolist(), "offset": plane.offset,
                  "inliers": plane.inliers, "inlier_share": plane.inlier_share,
                  "tolerance": plane.tolerance, "cameras_above": plane.cameras_above,
                  "points": cfg.plane_points,
                  "look_at_height": float(plane.height(look["point"]))},
        "selection": sel, "measures": meas, "masks": masks,
        "dataset_masks": len(given) if masks is None else masks["given"],
        "config": dataclasses.asdict(cfg),
    }


def summary_text(s: dict) -> str:
    """The report ``comgs cut`` prints."""
    p, look, me, sel = s["plane"], s["look_at"], s["measures"], s["selection"]
    how = (f"{len(sel['components'])} part(s) grown from the look-at point, linked within "
           f"{sel['link_radius']:.3g}: {sel['body']} above the slab, {sel['base']} base, "
           f"{sel['faint']} faint" if sel["method"] == "grow" else
           f"inside the box {sel['box']} ({sel['box_frame']} frame)")
    lines = [
        f"look-at point {_v(look['point'])}, scene size {look['scene_size']:.4g} (camera "
        f"axes spread {look['axes_spread_deg']:.1f}°)",
        f"plane: normal {_v(p['normal'])}, offset {p['offset']:.4g}, {p['inlier_share']:.1%} "
        f"of the nearby {'SfM points' if p['points'] == 'sfm' else 'opaque surfels'} within "
        f"{p['tolerance']:.3g}; look-at "
        f"{p['look_at_height']:.3g} above it, {p['cameras_above']:.0%} of the cameras above",
        f"kept {me['kept']} of {me['surfels']} surfels ({how}), height {me['height']:.4g}; "
        f"in the plane frame (--box-frame plane) they span "
        f"{' '.join(f'{v:.3g}' for v in me['plane_frame_box'])}",
        f"below the plane {me['below_share']:.2%} (opacity-weighted); in the slab "
        f"0–{me['slab_height']:.3g} above it {me['slab_share']:.2%}, lying flat there "
        f"{me['flat_slab_share']:.2%}",
    ]
    mk = s["masks"]
    if mk is not None:
        lines.append(f"masks: {mk['rendered']} rendered, {mk['given']} given"
                     + (f" (from {mk['given_folder']}, used as they are)" if mk["given"] else "")
                     + f"; mean coverage {mk['mean_coverage']:.1%}")
    elif s["dataset_masks"]:
        lines.append(f"the dataset ships {s['dataset_masks']} masks in masks/: --masks uses "
                     "them as they are")
    out = s["object_run"]
    lines.append(f"-> {out}/point_cloud.ply (object frame: plane z = 0, up +z), "
                 f"{out}/{CUT_FILE}")
    if mk is not None:
        lines.append(f"   object-only step 1: comgs reconstruct {out}/data --out RUN")
    return "\n".join(lines)


def _v(a) -> str:
    return "(" + ", ".join(f"{x:.3f}" for x in a) + ")"
