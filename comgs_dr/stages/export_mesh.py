"""``comgs export-mesh``: a triangle mesh from a reconstruction (what 2DGS is for).

Two methods:

* ``tsdf`` (2DGS's extraction): render depth, coverage and colour of the run's surfels
  from its training cameras (``surfel_gbuffer``, unbiased depth D/W), fuse them into a
  truncated signed distance grid with space carving (``core.tsdf``) and take the zero level
  set (marching cubes). Vertex colours: the fused rendered radiance, or the albedo after
  step 2 (sRGB-encoded for display).
* ``poisson``: screened Poisson reconstruction (pymeshlab) of the opaque surfel centres
  with their normals (oriented towards the nearest training camera); vertex colours from
  the surfels (SH DC radiance, or albedo). ``poisson_trim`` drops vertices below that
  quantile of the Poisson density (open scenes); 0 keeps a closed surface (objects).

Components with fewer than ``min_component_frac`` of the faces (floaters) are dropped. The
mesh is written atomically (PLY, OBJ or GLB by suffix, via trimesh) with a JSON sidecar of
the config, counts and timings.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np
from tqdm.auto import tqdm

from comgs_dr.core import runlog
from comgs_dr.core.cameras import camera_rays
from comgs_dr.core.colorspace import srgb_encode
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.tsdf import TSDFVolume
from comgs_dr.surfels import load_ply
from comgs_dr.surfels.io import quat_to_matrix
from comgs_dr.surfels.params import base_colour
from comgs_dr.surfels.params import object_bounds
from comgs_dr.surfels.scene import gbuffer_scene
from comgs_dr.train.losses import depth_to_normal
from comgs_dr.train.run import load_run_dataset, read_run_info, select_views

METHODS = ("tsdf", "poisson")
COLOURS = ("auto", "radiance", "albedo", "none")


@dataclass
class MeshConfig:
    """Mesh export settings (``PRESETS``: fast, default, fine).

    method: ``tsdf`` (default) or ``poisson``; resolution: TSDF voxels along the longest
    side, or the Poisson octree depth log2(N) (default 256); views: training views fused,
    evenly spread (default 64; None: all); trunc_voxels: TSDF truncation in voxels;
    max_normal_deg: tsdf skips pixels whose depth-derived and rendered normals differ by
    more (degrees); colour: ``auto`` (the albedo when step 2 ran, else the radiance),
    ``radiance``, ``albedo`` or ``none``; min_opacity: surfels used by poisson and for the
    bounds of both; poisson_trim: density quantile removed (0 keeps a closed surface);
    min_component_frac: components with fewer faces are dropped; padding: bounds grown by
    this fraction of their size.

    Example: ``export_mesh(run, "mesh.ply", MeshConfig(**PRESETS["fast"], colour="none"))``.
    """
    method: str = "tsdf"
    resolution: int = 256          # tsdf: voxels along the longest side; poisson: 2**depth ≥ N
    views: int | None = 64         # training views fused, evenly spread (None: all)
    trunc_voxels: float = 4.0      # TSDF truncation in voxels
    max_normal_deg: float = 30.0   # tsdf: pixels whose depth and normal disagree are skipped
    colour: str = "auto"           # auto: albedo when step 2 ran, else radiance
    max_hits: int = 32
    min_opacity: float = 0.2       # poisson: surfels used; bounds of both methods
    poisson_trim: float = 0.0      # poisson: density quantile removed (0: keep closed)
    min_component_frac: float = 0.01
    padding: float = 0.05          # bounds grown by this fraction of their size

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"MeshConfig.method must be one of {METHODS}, got {self.method!r}")
        if self.colour not in COLOURS:
            raise ValueError(f"MeshConfig.colour must be one of {COLOURS}, got {self.colour!r}")
        if not 8 <= self.resolution <= 1024:
            raise ValueError(f"MeshConfig.resolution must be in [8, 1024], got {self.resolution}")
        if self.views is not None and self.views < 1:
            raise ValueError(f"MeshConfig.views must be ≥ 1 or None, got {self.views}")
        for name in ("trunc_voxels", "padding", "max_normal_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"MeshConfig.{name} must be finite and > 0, got {v}")
        for name in ("poisson_trim", "min_component_frac", "min_opacity"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v < 1):
                raise ValueError(f"MeshConfig.{name} must be in [0, 1), got {v}")


PRESETS = {"fast": dict(resolution=128, views=24), "default": {},
           "fine": dict(resolution=512, views=None)}


def _surfels(run_dir: Path, colour: str):
    """(params, colour source 'radiance'|'albedo'|'none', ply path)."""
    mat = run_dir / "material" / "point_cloud.ply"
    if colour == "albedo" and not mat.is_file():
        raise FileNotFoundError(f"{mat} not found: --colour albedo needs step 2 "
                                "(`comgs decompose`) in the run folder")
    use_mat = colour == "albedo" or (colour == "auto" and mat.is_file())
    ply = mat if use_mat else run_dir / "point_cloud.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"{ply} not found: the run has not finished "
                                "(resume it with `comgs reconstruct`)")
    src = "none" if colour == "none" else ("albedo" if use_mat else "radiance")
    return load_ply(str(ply)), src, ply


def _bounds(params, cfg: MeshConfig) -> np.ndarray:
    lo, hi = object_bounds(params, min_opacity=cfg.min_opacity, q=0.2)
    pad = cfg.padding * float((hi - lo).max()) + 1e-6
    return np.stack([lo - pad, hi + pad])


def _to_display(rgb: np.ndarray, src: str) -> np.ndarray:
    """Vertex colours as display sRGB in [0, 1] (albedo is linear; radiance is stored sRGB)."""
    rgb = np.nan_to_num(rgb, nan=0.0, posinf=1.0, neginf=0.0)
    return np.clip(srgb_encode(np.clip(rgb, 0, 1)) if src == "albedo" else rgb, 0.0, 1.0)


def _consistent(depth, normal, dirs, origins, weight, max_deg: float) -> np.ndarray:
    """[H, W] bool: covered pixels whose depth-derived normal (``depth_to_normal``) agrees
    with the rendered normal within ``max_deg``. A pixel whose depth blends a surface with
    what shows through a hole in it fails: its depth lies between the two, off both, and
    fusing it would pull the surface there."""
    nd = np.asarray(depth_to_normal(to_jit(mi.TensorXf, depth),
                                    to_jit(mi.TensorXf, dirs),
                                    to_jit(mi.TensorXf, origins),
                                    weight=to_jit(mi.TensorXf, weight)))
    n = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-8)
    return (np.abs((n * nd).sum(-1)) >= math.cos(math.radians(max_deg))) & (weight > 0.5)


def _tsdf(params, views, bounds, cfg: MeshConfig, src: str, progress: bool,
          clip: dict | None = None):
    """Render every view's depth/coverage(/colour) and fuse them (``clip``: sensor clip
    planes, ``SceneData.clip_planes``)."""
    targets = "weight,depth_unbiased,normal" + {"radiance": ",color", "albedo": ",albedo"}.get(src, "")
    sensors = [v.camera.sensor_dict(**(clip or {})) for v in views]
    scene = gbuffer_scene(params, sensors, max_hits=cfg.max_hits, targets=targets)
    integ = scene.integrator()
    vol = TSDFVolume(bounds, cfg.resolution, cfg.trunc_voxels)
    for i in tqdm(range(len(views)), desc="export-mesh: fuse", unit="view", disable=not progress):
        b = {k: np.asarray(t) for k, t in integ.split(mi.render(scene, sensor=i)).items()}
        w = b["weight"][..., 0]
        cov = w > 0.5
        dirs, origins = (np.asarray(t) for t in camera_rays(sensors[i]))
        cam = views[i].camera
        hit = origins + b["depth_unbiased"][..., :1] * dirs                 # [H, W, 3]
        z = (hit - cam.center) @ cam.to_world[:3, 2]                        # Mitsuba +Z fwd
        known = _consistent(b["depth_unbiased"][..., 0], b["normal"], dirs, origins, w,
                            cfg.max_normal_deg)
        col = None
        if src != "none":
            key = "color" if src == "radiance" else "albedo"
            col = (b[key][..., :3] / np.maximum(w, 1e-6)[..., None]).astype(np.float32)
        vol.integrate(z.astype(np.float32), cov, cam.intrinsics(), cam.world_to_camera_cv(), col,
                      known=known | ~cov)
    verts, faces, colors = vol.extract()
    colors = None if colors is None else _to_display(colors, src)
    return verts, faces, colors, {"voxel": vol.voxel, "grid": list(vol.dims)}


def _poisson(params, views, cfg: MeshConfig, src: str):
    import pymeshlab  # heavy: only for this method
    d = params.to_numpy()
    op = 1.0 / (1.0 + np.exp(-d["opacity_logit"].astype(np.float64)))
    keep = (op >= cfg.min_opacity) & np.isfinite(d["means"]).all(1)
    if keep.sum() < 16:
        raise ValueError(f"export-mesh: only {int(keep.sum())} surfels with opacity ≥ "
                         f"{cfg.min_opacity}: too few for a Poisson surface")
    pts = d["means"][keep].astype(np.float64)                               # [N, 3]
    nrm = quat_to_matrix(d["quats"][keep])[:, :, 2]                         # [N, 3]
    centres = np.stack([v.camera.center for v in views])                   # [C, 3]
    nearest = centres[np.argmin(((pts[:, None] - centres[None]) ** 2).sum(-1), 1)]
    nrm *= np.where(((nearest - pts) * nrm).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    if src == "albedo":
        rgb = d["albedo"][keep]
    else:
        rgb = base_colour(d["sh"][keep])
    rgba = np.concatenate([_to_display(rgb, src), np.ones((len(pts), 1))], 1)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts, v_normals_matrix=nrm, v_color_matrix=rgba))
    depth = max(5, int(math.ceil(math.log2(cfg.resolution))))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, preclean=True)
    m = ms.current_mesh()
    if cfg.poisson_trim > 0:
        q = m.vertex_quality_array()
        ms.compute_selection_by_condition_per_vertex(
            condselect=f"q < {float(np.quantile(q, cfg.poisson_trim))}")
        ms.meshing_remove_selected_vertices()
        m = ms.current_mesh()
    colors = m.vertex_color_matrix()[:, :3] if src != "none" else None     # display sRGB
    return m.vertex_matrix(), m.face_matrix().astype(np.int64), colors, {"poisson_depth": depth}


def _drop_small(mesh, frac: float):
    """Keep the connected components with at least ``frac`` of the faces."""
    if frac <= 0 or len(mesh.faces) == 0:
        return mesh, 0
    parts = mesh.split(only_watertight=False)
    keep = [p for p in parts if len(p.faces) >= frac * len(mesh.faces)]
    if len(keep) == len(parts):
        return mesh, 0
    import trimesh
    return trimesh.util.concatenate(keep), len(parts) - len(keep)


def _write(mesh, out: Path) -> None:
    """Export atomically (format from the suffix)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=out.name + ".", suffix=out.suffix)
    os.close(fd)
    try:
        mesh.export(tmp)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def export_mesh(run_dir, out, cfg: MeshConfig = MeshConfig(), progress: bool = True) -> dict:
    """Extract and write the mesh of the run at ``run_dir``; returns the summary (also
    written to ``<out>.json``)."""
    import trimesh
    run_dir, out = Path(run_dir), Path(out)
    if out.suffix.lower() not in (".ply", ".obj", ".glb"):
        raise ValueError(f"export-mesh: {out} must end in .ply, .obj or .glb")
    t0 = time.perf_counter()
    info = read_run_info(run_dir)
    params, src, ply = _surfels(run_dir, cfg.colour)
    if params.count == 0:
        raise ValueError(f"export-mesh: {ply} has no surfels")
    data = load_run_dataset(run_dir, info, pixels=False)       # cameras only
    views = select_views(data.train, cfg.views)
    if cfg.method == "tsdf":
        verts, faces, colors, extra = _tsdf(params, views, _bounds(params, cfg), cfg, src,
                                            progress, data.clip_planes())
    else:
        verts, faces, colors, extra = _poisson(params, views, cfg, src)
    t_extract = time.perf_counter() - t0
    vc = None
    if colors is not None:
        c = np.clip(colors, 0.0, 1.0)                                       # display sRGB
        vc = np.concatenate([np.round(c * 255), np.full((len(c), 1), 255)], 1).astype(np.uint8)
    mesh = trimesh.Trimesh(verts, faces, vertex_colors=vc, process=True)
    mesh, dropped = _drop_small(mesh, cfg.min_component_frac)
    if len(mesh.faces) == 0:
        raise ValueError(f"export-mesh: the {cfg.method} surface of {ply} is empty")
    _write(mesh, out)
    summary = {"mesh": str(out), "method": cfg.method, "colour": src, "surfels": str(ply),
               "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
               "watertight": bool(mesh.is_watertight), "components_dropped": dropped,
               "views": len(views), "seconds": round(time.perf_counter() - t0, 2),
               "extract_seconds": round(t_extract, 2), **extra,
               "config": dataclasses.asdict(cfg)}
    Path(str(out) + ".json").write_text(json.dumps(runlog.json_safe(summary), indent=1,
                                                   allow_nan=False))
    return summary
