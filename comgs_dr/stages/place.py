"""``comgs place``: put an object on the surface of a reconstructed scene, from a pixel of
one of the scene's photos (or a point), and write its placement to ``transform.json``.

1. **Target**: the pixel's ray (the view's camera, the image's own pixel grid: pixel (X, Y)
   is column X, row Y from the top-left corner, the ray passes through its centre
   (X + ½, Y + ½)) is cast into the scene's surfels (``surfels.raycast``: the front-to-back
   composite of the ``surfel_gbuffer`` integrator); it hits where the accumulated opacity
   reaches ``min_weight``, at that surfel's depth (the median depth: the first surface;
   the composited mean depth also averages what lies behind it). ``--at X Y Z`` gives the point
   instead (the scene's ``point_cloud.ply`` frame).
2. **Normal**: a plane fitted to the centres of the scene's surfels (opacity ≥
   ``min_opacity``) within ``normal_radius`` × the placed object's size of the point
   (``sops.occlusion.plane_normals``: Tukey-reweighted, so a wall meeting the ground drops
   out), turned towards the camera (with ``--at``: the cameras' mean position). Fewer than
   3 surfels there: the normal of the surfel the ray hit.
3. **Up**: the normal, or world up (+Z) with ``upright`` — refused when the surface is
   tilted more than ``max_tilt_deg`` from horizontal.
4. **Pose**: the object's own frame has +Z up (as ``comgs cut`` writes it, and
   ``make-dataset``'s objects). Its *base* is the centre of its footprint at its lowest
   height: (x, y) the centre of its surfels' robust box (``surfels.params.object_bounds``),
   z the ``floater_share`` quantile of its opaque surfels' heights. The object is turned by
   ``yaw_deg`` about its own up, then by the smallest rotation taking +Z to the up vector,
   scaled by ``scale``, and its base put on the point.
5. **Lift**: one ray per opaque object surfel (at most ``max_rays``), cast along −up from
   above the placed object into the scene, finds the surface under it; the object is raised
   along up until all but ``floater_share`` of its surfels are above the surface (plus
   ``clearance`` × its size). A flat ground under an object placed along its normal needs no
   lift; an upright object on a slope, or an object across a step, is raised.
6. **Write**: ``transform.json`` gets (or replaces) the entry ``{name: {"transform":
   [16 floats, row-major]}}`` in the scene *dataset's* frame (``core.similarity``: what
   ``comgs compose --placement`` reads; it maps it to the world with the dataset's
   ``world_from_source``); other entries are kept as they are.

Errors (``PlaceError``, a ValueError naming the file or the flag): the ray hits nothing, the
surface is too steep for ``upright``, the object is larger than the scene, an unknown view,
a pixel outside the image, no surfel near ``--at`` without ``upright``.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from comgs_dr.core.similarity import Similarity, read_placements
from comgs_dr.data.load import load_dataset
from comgs_dr.data.types import MITSUBA_FROM_OPENCV, rotation_to_z
from comgs_dr.sops.occlusion import plane_normals
from comgs_dr.surfels import raycast
from comgs_dr.surfels.io import load_ply
from comgs_dr.surfels.params import SurfelParams, object_bounds
from comgs_dr.train.run import check_run_cameras, read_run_info

log = logging.getLogger(__name__)

WORLD_UP = np.array([0.0, 0.0, 1.0])


class PlaceError(ValueError):
    """An input ``comgs place`` cannot use (exit 2 with the message)."""


@dataclasses.dataclass
class PlaceConfig:
    """Settings of ``comgs place``. Lengths are fractions of the *placed* object's size (the
    diagonal of its opaque surfels' robust box × ``scale``).

    scale: the object's uniform scale in the scene (> 0).
    yaw_deg: turn (degrees) about the object's own up axis before it is stood on the surface.
    upright: stand the object along world up (+Z) instead of the surface normal.
    max_tilt_deg: with ``upright``, the steepest surface accepted (degrees from horizontal).
    min_weight: a ray hits where its accumulated opacity reaches this (0–1, exclusive).
    normal_radius: scene surfels this close to the point fit the surface plane (× size).
    min_opacity: fainter surfels (opacity 0–1) are ignored for the normal, the object's base
        and size.
    floater_share: share of the object's surfels allowed below its base and under the
        surface (stray floaters); 0: every surfel counts.
    clearance: gap left between the object's lowest surfels and the surface (× size).
    max_rays: object surfels whose footprint is traced down for the lift (a random subset
        when there are more).
    max_hits: surfels composited per ray and pass.
    seed: seed of that subset.
    """
    scale: float = 1.0
    yaw_deg: float = 0.0
    upright: bool = False
    max_tilt_deg: float = 30.0
    min_weight: float = 0.5
    normal_radius: float = 0.25
    min_opacity: float = 0.1
    floater_share: float = 0.002
    clearance: float = 0.0
    max_rays: int = 20000
    max_hits: int = 16
    seed: int = 0

    def __post_init__(self):
        for name in ("scale", "normal_radius"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise PlaceError(f"PlaceConfig.{name} must be a finite number > 0, got {v!r}")
        if not math.isfinite(self.yaw_deg):
            raise PlaceError(f"PlaceConfig.yaw_deg must be finite, got {self.yaw_deg!r}")
        if not 0.0 < self.max_tilt_deg <= 90.0:
            raise PlaceError(f"PlaceConfig.max_tilt_deg must be in (0, 90], got "
                             f"{self.max_tilt_deg!r}")
        if not 0.0 < self.min_weight < 1.0:
            raise PlaceError(f"PlaceConfig.min_weight must be in (0, 1), got {self.min_weight!r}")
        if not 0.0 <= self.min_opacity < 1.0:
            raise PlaceError(f"PlaceConfig.min_opacity must be in [0, 1), got {self.min_opacity!r}")
        if not 0.0 <= self.floater_share < 0.5:
            raise PlaceError(f"PlaceConfig.floater_share must be in [0, 0.5), got "
                             f"{self.floater_share!r}")
        if not (math.isfinite(self.clearance) and self.clearance >= 0):
            raise PlaceError(f"PlaceConfig.clearance must be >= 0, got {self.clearance!r}")
        if self.max_rays < 1 or self.max_hits < 1:
            raise PlaceError("PlaceConfig.max_rays and max_hits must be >= 1")


# ----------------------------------------------------------------------------- geometry

def pixel_ray(camera, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
    """(origin [3], unit direction [3]) of the ray through the centre of pixel (x, y) of
    ``camera`` (a ``data.types.Camera``; column x, row y from the image's top-left corner)."""
    fx = camera.fx
    fy = fx * float(camera.fy_over_fx)
    d_cv = np.array([(x + 0.5 - camera.cx) / fx, (y + 0.5 - camera.cy) / fy, 1.0])
    c2w = camera.to_world @ MITSUBA_FROM_OPENCV
    d = c2w[:3, :3] @ d_cv
    return camera.center, d / np.linalg.norm(d)


def surfel_arrays(params: SurfelParams) -> tuple[np.ndarray, np.ndarray]:
    """(centres [N, 3] float64, opacities [N]) of a surfel set."""
    d = params.to_numpy()
    op = 1.0 / (1.0 + np.exp(-d["opacity_logit"].astype(np.float64).reshape(-1)))
    return d["means"].astype(np.float64), op


@dataclasses.dataclass
class ObjectShape:
    """What placing needs of an object, in its own frame (+Z up)."""
    points: np.ndarray          # [M, 3] opaque surfel centres (finite)
    base: np.ndarray            # [3] centre of the footprint at the lowest height
    size: float                 # diagonal of the robust box (unscaled)
    height: float               # base to the top quantile (unscaled)


def object_shape(params: SurfelParams, cfg: PlaceConfig, where: str = "object") -> ObjectShape:
    """The object's opaque surfels, base point and size (module docstring, step 4)."""
    means, op = surfel_arrays(params)
    keep = (op >= cfg.min_opacity) & np.isfinite(means).all(1)
    pts = means[keep]
    if len(pts) < 4:
        raise PlaceError(f"{where}: {len(pts)} surfel(s) with opacity >= {cfg.min_opacity}: "
                         "nothing to place")
    lo, hi = object_bounds(params, cfg.min_opacity)
    q = 100.0 * cfg.floater_share
    z0, z1 = np.percentile(pts[:, 2], [q, 100.0 - q])
    base = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, z0])
    return ObjectShape(pts, base, float(np.linalg.norm(hi - lo)), float(z1 - z0))


def up_rotation(up, yaw_deg: float = 0.0) -> np.ndarray:
    """R [3, 3] = (smallest rotation taking +Z to ``up``) · R_z(yaw)."""
    a = math.radians(yaw_deg)
    rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                   [0.0, 0.0, 1.0]])
    return rotation_to_z(up).T @ rz


def pose(shape: ObjectShape, point, up, cfg: PlaceConfig) -> Similarity:
    """The object→world similarity standing ``shape``'s base on ``point`` along ``up``."""
    r = up_rotation(up, cfg.yaw_deg)
    t = np.asarray(point, np.float64) - cfg.scale * (r @ shape.base)
    return Similarity(float(cfg.scale), r, t)


def tilt_deg(normal) -> float:
    """Angle (degrees) between ``normal`` and world up."""
    n = np.asarray(normal, np.float64)
    return float(np.degrees(np.arccos(np.clip(n @ WORLD_UP / np.linalg.norm(n), -1.0, 1.0))))


def surface_normal(scene_points, point, radius: float, towards, fallback=None) -> tuple:
    """(unit normal [3] of the plane fitted to ``scene_points`` within ``radius`` of
    ``point``, turned to the side of ``towards``; neighbours used). Fewer than 3 of them:
    ``fallback`` (None: PlaceError is left to the caller, returned as (None, n))."""
    p = np.asarray(point, np.float64)
    near = scene_points[np.linalg.norm(scene_points - p, axis=1) <= radius]
    towards = np.asarray(towards, np.float64)
    if len(near) < 3:
        return (None if fallback is None else np.asarray(fallback, np.float64)), len(near)
    n = plane_normals(near, np.broadcast_to(towards, near.shape), p[None], radius)[0]
    if n @ towards < 0:
        n = -n
    return n, len(near)


def lift(scene_trace, placed_points, up, top: float, cfg: PlaceConfig, size: float,
         origin) -> dict:
    """How far to raise the placed object along ``up`` so that all but ``floater_share`` of
    its surfels ``placed_points`` [M, 3] (world) are above the scene's surface.

    Each surfel's footprint is traced along −up from ``top`` (a height along up, from
    ``origin``, above the placed object) into ``scene_trace``; where it hits (weight ≥
    ``min_weight``) the surface height s is known and the surfel's penetration is s − h.
    Returns {"lift", "rays", "hits", "max_penetration" (before the lift), "below" (surfels
    still under the surface after it, as a share)}."""
    up = np.asarray(up, np.float64)
    pts = np.asarray(placed_points, np.float64)
    if len(pts) > cfg.max_rays:
        pts = pts[np.random.default_rng(cfg.seed).choice(len(pts), cfg.max_rays, replace=False)]
    h = (pts - origin) @ up                                      # heights along up
    starts = pts + (top - h)[:, None] * up
    r = raycast.cast(scene_trace, starts, np.broadcast_to(-up, starts.shape), cfg.max_hits,
                     level=cfg.min_weight)
    hit = np.isfinite(r["depth"])
    s = top - np.where(hit, r["depth"], 0.0)
    pen = np.where(hit, s - h, -np.inf)
    if not hit.any():
        return {"lift": cfg.clearance * size, "rays": int(len(pts)), "hits": 0,
                "max_penetration": 0.0, "below": 0.0}
    q = np.quantile(pen[hit], 1.0 - cfg.floater_share) if cfg.floater_share > 0 else \
        float(pen[hit].max())
    amount = max(0.0, float(q)) + cfg.clearance * size
    return {"lift": amount, "rays": int(len(pts)), "hits": int(hit.sum()),
            "max_penetration": float(max(0.0, pen[hit].max())),
            "below": float(np.mean(pen > amount))}


@dataclasses.dataclass
class Target:
    """Where the object goes: the surface point and how it was found."""
    point: np.ndarray                   # [3] world
    towards: np.ndarray                 # [3] unit, from the surface to the viewer
    ray_normal: np.ndarray | None       # the normal of the surfel the pixel's ray hit
    record: dict                        # what the summary reports


def pixel_target(scene_trace, camera, x: float, y: float, cfg: PlaceConfig,
                 where: str = "view") -> Target:
    """Cast the pixel's ray into the scene; PlaceError when it hits nothing."""
    if not (0.0 <= x < camera.width and 0.0 <= y < camera.height):
        raise PlaceError(f"{where}: pixel ({x:g}, {y:g}) is outside the {camera.width}×"
                         f"{camera.height} image")
    o, d = pixel_ray(camera, x, y)
    r = raycast.cast(scene_trace, o[None], d[None], cfg.max_hits, level=cfg.min_weight)
    w = float(r["weight"][0])
    if not np.isfinite(r["depth"][0]):
        raise PlaceError(f"{where}: the ray of pixel ({x:g}, {y:g}) hits nothing (accumulated "
                         f"opacity {w:.3f} < min_weight {cfg.min_weight}): pick a pixel on "
                         "the reconstructed surface")
    t = float(r["depth"][0])
    return Target(o + t * d, -d, r["normal"][0],
                  {"pixel": [float(x), float(y)], "ray_origin": o.tolist(),
                   "ray_direction": d.tolist(), "depth": t,
                   "mean_depth": float(r["mean_depth"][0]), "opacity": w})


def place_object(scene_params: SurfelParams, obj_params: SurfelParams, target: Target,
                 cfg: PlaceConfig, scene_trace=None, where: str = "scene") -> dict:
    """The placement of the object (world frame) on ``target``: {"similarity", "base",
    "normal", "up", "tilt_deg", "lift", ...} (module docstring, steps 2–5)."""
    if scene_trace is None:
        scene_trace = raycast.trace_scene(scene_params)
    shape = object_shape(obj_params, cfg)
    size = shape.size * cfg.scale
    means, op = surfel_arrays(scene_params)
    solid = means[(op >= cfg.min_opacity) & np.isfinite(means).all(1)]
    if len(solid) == 0:
        raise PlaceError(f"{where}: no surfel with opacity >= {cfg.min_opacity}")
    scene_size = float(np.linalg.norm(np.subtract(*object_bounds(scene_params,
                                                                 cfg.min_opacity)[::-1])))
    if size > scene_size:
        raise PlaceError(f"{where}: the object at scale {cfg.scale:g} is {size:.4g} across, "
                         f"larger than the scene ({scene_size:.4g}): lower --scale")
    fallback = target.ray_normal if target.ray_normal is not None and \
        np.linalg.norm(target.ray_normal) > 0 else None
    normal, near = surface_normal(solid, target.point, cfg.normal_radius * size,
                                  target.towards, fallback)
    if normal is None:
        if not cfg.upright:
            raise PlaceError(f"{where}: no surfel within {cfg.normal_radius * size:.4g} of "
                             f"{np.round(target.point, 4).tolist()}: no surface to stand on "
                             "there (use --upright to stand it along world up)")
        normal = WORLD_UP.copy()
    tilt = tilt_deg(normal)
    if cfg.upright and tilt > cfg.max_tilt_deg:
        raise PlaceError(f"{where}: the surface at {np.round(target.point, 4).tolist()} is "
                         f"tilted {tilt:.1f}° from horizontal, steeper than max_tilt_deg "
                         f"{cfg.max_tilt_deg:g}° for --upright (drop --upright to stand the "
                         "object along the normal, or raise --max-tilt-deg)")
    up = WORLD_UP.copy() if cfg.upright else normal
    sim = pose(shape, target.point, up, cfg)
    placed = sim.points(shape.points)
    # rays start above the object and above the surface under its footprint (which rises
    # by up to the footprint's reach × tan(angle between up and the normal))
    slope = math.radians(min(float(np.degrees(np.arccos(np.clip(up @ normal, -1, 1)))), 80.0))
    top = float(((placed - target.point) @ up).max()) + size * (0.05 + math.tan(slope))
    lf = lift(scene_trace, placed, up, top, cfg, size, target.point)
    sim = Similarity(sim.scale, sim.rotation, sim.translation + lf["lift"] * up)
    base = target.point + lf["lift"] * up
    angle = None
    if target.ray_normal is not None and np.linalg.norm(target.ray_normal) > 0:
        angle = float(np.degrees(np.arccos(np.clip(normal @ target.ray_normal, -1, 1))))
    return {"similarity": sim, "hit": target.point, "base": base, "normal": normal, "up": up,
            "tilt_deg": tilt, "normal_neighbours": int(near), "ray_normal_angle_deg": angle,
            "object_size": size, "scene_size": scene_size, "lift": lf,
            "target": target.record}


# ----------------------------------------------------------------------------- files

def find_view(views: list, spec: str, where: str):
    """The view named ``spec`` (its name, image file name or stem) or at index ``spec``."""
    s = str(spec)
    for v in views:
        p = Path(v.path) if v.path else None
        if s in (v.name, Path(v.name).name) or (p is not None and s in (p.name, p.stem)):
            return v
    if s.lstrip("-").isdigit():
        i = int(s)
        if -len(views) <= i < len(views):
            return views[i]
        raise PlaceError(f"{where}: view index {i} is out of range (the capture has "
                         f"{len(views)} views, 0–{len(views) - 1})")
    names = ", ".join(v.name for v in views[:6]) + (", ..." if len(views) > 6 else "")
    raise PlaceError(f"{where}: no view {s!r} (an image name or an index 0–{len(views) - 1}; "
                     f"views: {names})")


def object_ply(run) -> Path:
    """The object's surfels: ``RUN/material/point_cloud.ply`` (step 2) or
    ``RUN/point_cloud.ply`` (step 1), or RUN itself when it is a .ply file."""
    run = Path(run)
    if run.is_file() and run.suffix.lower() == ".ply":
        return run
    for p in (run / "material" / "point_cloud.ply", run / "point_cloud.ply"):
        if p.is_file():
            return p
    raise FileNotFoundError(f"{run}: no point_cloud.ply in it or in {run / 'material'} "
                            "(an object run of `comgs reconstruct`/`decompose`/`cut`)")


def to_source_frame(sim: Similarity, world_from_source) -> Similarity:
    """The world placement in the dataset's own frame (compose maps it back with ``W``)."""
    W = np.asarray(world_from_source, np.float64)
    rt = W[:3, :3].T
    return Similarity(sim.scale, rt @ sim.rotation, rt @ (sim.translation - W[:3, 3]))


def write_entry(path, name: str, sim: Similarity) -> bool:
    """Add or replace ``name`` in the placement file ``path`` (other entries kept as they
    are); returns whether an entry was replaced. The file is checked by
    ``core.similarity.read_placements`` before it is changed."""
    p = Path(path)
    data = {}
    if p.exists():
        read_placements(p)                        # a broken file is an error, not overwritten
        data = json.loads(p.read_text(encoding="utf-8"))
    replaced = name in data
    data[name] = {"transform": sim.matrix.ravel().tolist()}
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + f".tmp{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=1), encoding="utf-8")
    tmp.replace(p)
    return replaced


def place(scene_run, name: str, object_run, out, *, view=None, pixel=None, at=None,
          cfg: PlaceConfig | None = None, say: Callable[[str], object] = log.info) -> dict:
    """Place object ``name`` (surfels of ``object_run``) in step-1 run ``scene_run`` at the
    pixel ``pixel`` = (x, y) of view ``view`` (name or index) or at point ``at`` (world, the
    run's point_cloud.ply frame), and add it to the placement file ``out``. Returns the
    summary (also what ``say`` reports line by line)."""
    cfg = cfg or PlaceConfig()
    t0 = clock = time.perf_counter()
    seconds = {}

    def lap(key):
        nonlocal clock
        now = time.perf_counter()
        seconds[key], clock = round(now - clock, 4), now

    if not name or not name.replace("_", "").replace("-", "").isalnum():
        raise PlaceError(f"object names must be letters, digits, '-' or '_', got "
                         f"{name!r}")
    if (at is None) == (pixel is None):
        raise PlaceError("give --view VIEW --pixel X Y, or --at X Y Z")
    if pixel is not None and view is None:
        raise PlaceError("--pixel needs --view (an image name or index)")
    scene_run = Path(scene_run)
    info = read_run_info(scene_run)
    ply = scene_run / "point_cloud.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"{ply} not found: finish step 1 on the scene first")
    scene_params = load_ply(ply)
    oply = object_ply(object_run)
    obj_params = load_ply(oply)
    check_run_cameras(scene_run, info)
    data = load_dataset(info["data"], pixels=False)             # full-resolution cameras
    lap("load")
    trace = raycast.trace_scene(scene_params)
    if pixel is not None:
        v = find_view(data.train + data.test, view, f"{info['data']}")
        target = pixel_target(trace, v.camera, float(pixel[0]), float(pixel[1]), cfg,
                              where=f"view {v.name!r} ({info['data']})")
        target.record["view"] = v.name
    else:
        p = np.asarray(at, np.float64).reshape(3)
        if not np.isfinite(p).all():
            raise PlaceError(f"--at needs 3 finite numbers, got {list(at)}")
        cams = np.array([v.camera.center for v in data.train + data.test]).reshape(-1, 3)
        towards = (cams.mean(0) - p) if len(cams) else WORLD_UP
        towards = towards / max(np.linalg.norm(towards), 1e-30)
        target = Target(p, towards, None, {"at": p.tolist()})
    lap("target")
    res = place_object(scene_params, obj_params, target, cfg, trace, where=str(ply))
    lap("place")
    src = to_source_frame(res["similarity"], data.world_from_source)
    replaced = write_entry(out, name, src)
    lap("write")
    seconds["total"] = round(time.perf_counter() - t0, 4)
    summary = {
        "name": name, "scene_run": str(scene_run), "object": str(oply), "out": str(out),
        "replaced": replaced, "target": target.record,
        "hit": res["hit"].tolist(), "base": res["base"].tolist(),
        "normal": res["normal"].tolist(), "up": res["up"].tolist(),
        "tilt_deg": res["tilt_deg"], "normal_neighbours": res["normal_neighbours"],
        "ray_normal_angle_deg": res["ray_normal_angle_deg"],
        "object_size": res["object_size"], "scene_size": res["scene_size"],
        "lift": res["lift"], "transform": src.matrix.ravel().tolist(),
        "world_transform": res["similarity"].matrix.ravel().tolist(),
        "config": dataclasses.asdict(cfg), "seconds": seconds,
    }
    for line in summary_lines(summary):
        say(line)
    return summary


def _v(a) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in a) + ")"


def summary_lines(s: dict) -> list[str]:
    """The lines ``comgs place`` prints."""
    t, lf = s["target"], s["lift"]
    how = (f"view {t['view']!r} pixel ({t['pixel'][0]:g}, {t['pixel'][1]:g}): ray hits at "
           f"depth {t['depth']:.4g} (opacity {t['opacity']:.2f})" if "pixel" in t else
           f"at {_v(t['at'])}")
    ang = s["ray_normal_angle_deg"]
    return [
        f"{how}, point {_v(s['hit'])}",
        f"surface normal {_v(s['normal'])} (plane of {s['normal_neighbours']} surfels"
        + (f"; {ang:.1f}° from the hit surfel's own normal" if ang is not None else "")
        + f"), tilt {s['tilt_deg']:.1f}° from world up",
        f"up {_v(s['up'])} ({'world up, --upright' if s['config']['upright'] else 'normal'}), "
        f"yaw {s['config']['yaw_deg']:g}°, scale {s['config']['scale']:g}: object "
        f"{s['object_size']:.4g} across (scene {s['scene_size']:.4g})",
        f"lift {lf['lift']:.4g} along up ({lf['hits']} of {lf['rays']} rays under the object "
        f"hit the surface; deepest surfel {lf['max_penetration']:.4g} under it before, "
        f"{lf['below']:.2%} still under after)",
        f"base {_v(s['base'])}; {'replaced' if s['replaced'] else 'wrote'} {s['name']!r} in "
        f"{s['out']} ({s['seconds']['total']:.2f} s)",
    ]
