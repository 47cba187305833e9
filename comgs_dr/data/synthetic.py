"""Synthetic ground truth for objects (SynCom-Object protocol, paper appendix A).

An object mesh is normalised into a box centred at the origin (Z-up), lit by an HDR
environment map and rendered with Mitsuba's ``path`` integrator. Training cameras are
uniformly random on the upper hemisphere, test cameras on three latitude circles, all
looking at the origin. The output is a NeRF-synthetic folder::

    transforms_train.json, transforms_test.json, meta.json
    train/r_<i>.png                 RGBA, 8-bit sRGB, straight alpha = pixel coverage
    test/r_<i>.png, r_<i>.exr       the same + linear HDR radiance (RGBA, premultiplied)
    test/r_<i>_{albedo,normal,depth}.exr   linear G-buffer ground truth
    test_relight/<map>/r_<i>.{png,exr}     test views relit under each held-out map

``transform_matrix`` follows NeRF/Blender (OpenGL camera: looks down -Z, +Y up, +X
right); each frame also stores Mitsuba's sensor ``to_world`` (+Z forward, +X left)
under ``to_world_mitsuba``; ``to_world_mitsuba = transform_matrix @ diag(-1, 1, -1, 1)``.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np
from tqdm.auto import tqdm

from comgs_dr.core.variant import package_version
from comgs_dr.data import synthetic_io as sio
from comgs_dr.data.detail_mesh import write_detail_mesh
from comgs_dr.data.sfm_points import sample_visible_points, write_points_ply
from comgs_dr.lighting.envmap import load_envmap

GENERATOR_VERSION = "comgs_dr.eval.synthetic/1"

#: Poly Haven maps of the shared data set that may light training data (4 of 6).
TRAIN_ENVMAPS = ("forest_slope_1k.hdr", "adams_place_bridge_1k.hdr",
                 "empty_warehouse_01_1k.hdr", "kiara_1_dawn_1k.hdr")
#: Maps kept out of anything used for fitting; the default relighting targets.
HELDOUT_ENVMAPS = ("st_fagans_interior_1k.hdr", "venice_sunset_1k.hdr")
DEFAULT_ENVMAP = TRAIN_ENVMAPS[0]
DEFAULT_MESH = "meshes/spot_triangulated.obj"
#: Directory of the shared sample data, beside a source checkout (``<repo>/../shared/data``);
#: override with $COMGS_DATA_DIR.
DEFAULT_DATA_DIR = str(Path(__file__).resolve().parents[3] / "shared" / "data")

#: Equirect orientation (Blender's, Z-up): world direction d maps to
#: u = 0.5 - atan2(d_y, d_x) / 2pi, v = acos(d_z) / pi (v = 0 is the top row).
#: Mitsuba's envmap is Y-up with u = atan2(l_x, -l_z) / 2pi; this rotation sends
#: its local frame to world: (l_x, l_y, l_z) -> world (l_z, l_x, l_y).
ENVMAP_TO_WORLD = np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
#: +Y-up mesh files -> +Z-up world: rotation by +90 deg about X, (x, y, z) -> (x, -z, y).
Y_UP_TO_Z_UP = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
GL_FROM_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])  # flips camera X and Z (self-inverse)


BUILTIN_DETAIL_MESH = "detail"   # ``mesh="detail"``: :mod:`comgs_dr.data.detail_mesh`


def shared_data_dir() -> Path:
    """The shared sample-data directory ($COMGS_DATA_DIR or ``<repo>/../shared/data``); may not exist."""
    return Path(os.environ.get("COMGS_DATA_DIR", DEFAULT_DATA_DIR))


def shared_envmap(name: str) -> Path:
    """Path of one of the shared HDRIs (``TRAIN_ENVMAPS`` / ``HELDOUT_ENVMAPS``)."""
    return shared_data_dir() / "hdri" / name


def default_mesh() -> Path:
    """The shared sample mesh (Spot); FileNotFoundError with a hint if it is missing."""
    p = shared_data_dir() / DEFAULT_MESH
    if not p.is_file():
        raise FileNotFoundError(f"no mesh given and the default sample mesh {p} does not exist; "
                                "pass a mesh path (--mesh) or set $COMGS_DATA_DIR")
    return p


def default_envmap() -> Path:
    """The default (training) lighting map; FileNotFoundError with a hint if it is missing."""
    p = shared_envmap(DEFAULT_ENVMAP)
    if not p.is_file():
        raise FileNotFoundError(f"no envmap given and the default map {p} does not exist; "
                                "pass an .hdr/.exr path (--envmap) or set $COMGS_DATA_DIR")
    return p


@dataclass
class ObjectDatasetConfig:
    """Settings of :func:`make_object_dataset` (sizes default to a ~1-2 min CPU run).

    ``mesh``/``envmap`` None: the shared sample data (error if absent).
    ``relight_envmaps`` None: ``HELDOUT_ENVMAPS`` when present in the shared data, else none;
    pass ``()`` for no relighting. ``radius`` None: fit the object's bounding sphere into
    the field of view with ``radius_margin``. ``texture`` "auto": an ``.mtl`` ``map_Kd`` or a
    sibling image named like the mesh (``spot_triangulated.obj`` -> ``spot_texture.png``);
    None: constant ``base_color``. ``up_axis`` is the mesh file's up axis ("y" or "z").
    """
    mesh: str | Path | None = None
    envmap: str | Path | None = None
    out_dir: str | Path = "syncom_object"
    n_train: int = 100
    n_test: int = 24
    resolution: int = 128
    spp: int = 64
    spp_test: int | None = None          # None: 2 * spp (test ground truth)
    spp_aov: int = 32
    max_depth: int = 8
    relight_envmaps: tuple | list | None = None
    envmap_scale: float = 1.0
    seed: int = 0
    fov_deg: float = 40.0                # horizontal = vertical (square images)
    radius: float | None = None
    radius_margin: float = 1.1
    train_elevation_deg: tuple[float, float] = (0.0, 90.0)
    train_rings_deg: tuple[float, ...] = ()  # non-empty: train views on these elevation rings
    test_elevations_deg: tuple[float, ...] = (15.0, 35.0, 55.0)
    up_axis: str = "y"
    half_extent: float = 1.0             # largest half side of the normalised bounding box
    texture: str | Path | None = "auto"
    base_color: tuple[float, float, float] = (0.6, 0.6, 0.6)  # linear, without texture
    roughness: float = 0.5
    metallic: float = 0.0
    variant: str | None = None           # None: keep the active JIT variant, else set it
    sfm_points: int = 0                  # > 0: write points3d.ply (SfM-like, ``sfm_points``)

    def __post_init__(self):
        for name in ("n_train", "n_test"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"ObjectDatasetConfig.{name} must be >= 1 "
                                 f"(got {getattr(self, name)})")
        if int(self.resolution) < 8:
            raise ValueError(f"ObjectDatasetConfig.resolution must be >= 8 (got {self.resolution})")
        for name in ("spp", "spp_aov", "max_depth"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"ObjectDatasetConfig.{name} must be >= 1 "
                                 f"(got {getattr(self, name)})")
        if self.spp_test is not None and int(self.spp_test) < 1:
            raise ValueError(f"ObjectDatasetConfig.spp_test must be >= 1 (got {self.spp_test})")
        if not 1.0 < float(self.fov_deg) < 170.0:
            raise ValueError("ObjectDatasetConfig.fov_deg must be in (1, 170) "
                             f"(got {self.fov_deg})")
        if self.up_axis not in ("y", "z"):
            raise ValueError("ObjectDatasetConfig.up_axis must be 'y' or 'z' "
                             f"(got {self.up_axis!r})")
        lo, hi = self.train_elevation_deg
        if not -90.0 <= lo <= hi <= 90.0:
            raise ValueError("ObjectDatasetConfig.train_elevation_deg must satisfy "
                             f"-90 <= lo <= hi <= 90 (got {self.train_elevation_deg})")
        if any(not -90.0 <= float(e) <= 90.0 for e in self.train_rings_deg):
            raise ValueError("ObjectDatasetConfig.train_rings_deg must be elevations in [-90, 90] "
                             f"(got {self.train_rings_deg})")
        if not self.test_elevations_deg:
            raise ValueError("ObjectDatasetConfig.test_elevations_deg must name >= 1 circle")
        if self.radius is not None and float(self.radius) <= 0:
            raise ValueError(f"ObjectDatasetConfig.radius must be > 0 (got {self.radius})")


@dataclass
class SceneDatasetConfig:
    """Sizes of ``comgs make-dataset scene``: the procedural table-top scene
    (``data.procedural.scene_dataset_config``, which fixes everything else) with SfM-like
    points, the scene preset's test case.

    n_train / n_test: training / test views (default 60 / 12); resolution: image side in
    pixels (default 96); points: SfM-like points in ``points3d.ply`` (default 20000; 0: no
    file); seed: camera, point and noise seed (default 0).
    """
    n_train: int = 60
    n_test: int = 12
    resolution: int = 96
    points: int = 20_000
    seed: int = 0

    def __post_init__(self):
        if int(self.points) < 0:
            raise ValueError(f"SceneDatasetConfig.points must be >= 0 (got {self.points})")


# ----------------------------------------------------------------------------- cameras

def look_at(origin, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Mitsuba sensor ``to_world`` (4x4; columns left, up, forward, origin).

    Same as ``mi.ScalarTransform4f().look_at`` but falls back to +Y as ``up`` when the
    view direction is (anti)parallel to ``up`` (a camera at the zenith).
    """
    o, t = np.asarray(origin, float), np.asarray(target, float)
    d = (t - o) / np.linalg.norm(t - o)
    left = np.cross(np.asarray(up, float), d)
    if np.linalg.norm(left) < 1e-6:
        left = np.cross([0.0, 1.0, 0.0], d)
    left /= np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(d, left), d, o
    return m


def _direction(elev_deg, azim_deg) -> np.ndarray:
    e, a = np.radians(elev_deg), np.radians(azim_deg)
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)


def train_cameras(n: int, radius: float, rng: np.random.Generator,
                  elevation_deg=(0.0, 90.0)) -> list[dict]:
    """``n`` cameras uniform in area on the spherical zone between the two elevations."""
    zlo, zhi = np.sin(np.radians(elevation_deg))
    z = rng.uniform(zlo, zhi, n)
    azim = rng.uniform(0.0, 360.0, n)
    elev = np.degrees(np.arcsin(z))
    return [_camera(radius, e, a) for e, a in zip(elev, azim)]


def test_cameras(n: int, radius: float, elevations_deg=(15.0, 35.0, 55.0)) -> list[dict]:
    """``n`` cameras on latitude circles, evenly spaced in azimuth (circle k gets
    ``n // K`` views, the first ``n % K`` circles one more; staggered start angles)."""
    k = len(elevations_deg)
    cams = []
    for c, elev in enumerate(elevations_deg):
        m = n // k + (1 if c < n % k else 0)
        for j in range(m):
            cams.append(_camera(radius, elev, 360.0 * (j + c / k) / m))
    return cams


def _camera(radius, elev, azim) -> dict:
    m = look_at(radius * _direction(elev, azim))
    return {"elevation_deg": float(elev), "azimuth_deg": float(azim % 360.0),
            "to_world_mitsuba": m, "transform_matrix": m @ GL_FROM_MITSUBA}


# ----------------------------------------------------------------------------- object

def object_transform(vertices: np.ndarray, up_axis: str = "y", half_extent: float = 1.0):
    """4x4 mesh->world transform: centre the bounding box, rotate to Z-up, scale the
    largest half side to ``half_extent``. Returns (matrix, bounding-sphere radius)."""
    lo, hi = vertices.min(0), vertices.max(0)
    if not np.all(np.isfinite([lo, hi])) or np.max(hi - lo) <= 0:
        raise ValueError("object mesh has a degenerate or non-finite bounding box")
    t = np.eye(4)
    t[:3, 3] = -(lo + hi) / 2
    s = np.diag([2 * half_extent / np.max(hi - lo)] * 3 + [1.0])
    rot = Y_UP_TO_Z_UP if up_axis == "y" else np.eye(4)
    m = s @ rot @ t
    v = vertices @ m[:3, :3].T + m[:3, 3]
    return m, float(np.linalg.norm(v, axis=1).max())


def find_texture(mesh_path) -> Path | None:
    """Albedo texture of a mesh: ``map_Kd`` of its .mtl, else a sibling image named
    ``<stem>[_texture|_albedo|_diffuse].{png,jpg}`` (also with the stem cut at '_')."""
    p = Path(mesh_path)
    if p.suffix.lower() == ".obj":
        with open(p, errors="ignore") as f:
            mtls = [ln.split(None, 1)[1].strip() for ln in f if ln.startswith("mtllib ")]
        for mtl in mtls:
            mp = p.parent / mtl
            if mp.is_file():
                for ln in mp.read_text(errors="ignore").splitlines():
                    if ln.strip().startswith("map_Kd"):
                        tex = p.parent / ln.split()[-1]
                        if tex.is_file():
                            return tex
    for stem in dict.fromkeys([p.stem, p.stem.split("_")[0]]):
        for suffix in ("_texture", "_albedo", "_diffuse", ""):
            for ext in (".png", ".jpg", ".jpeg"):
                cand = p.parent / f"{stem}{suffix}{ext}"
                if cand.is_file():
                    return cand
    return None


# ----------------------------------------------------------------------------- driver

def make_object_dataset(cfg: ObjectDatasetConfig, progress: bool = True) -> dict:
    """Render a NeRF-synthetic style object dataset into ``cfg.out_dir``.

    Returns a summary dict (out_dir, counts, radius, relight map names, seconds).
    Raises FileNotFoundError for missing inputs, ValueError for unreadable or
    non-finite environment maps and invalid settings.
    """
    t0 = time.perf_counter()
    cfg = dataclasses.replace(cfg)  # re-validates numeric fields
    src = _object_inputs(cfg)
    rng = np.random.default_rng(cfg.seed)
    cams = {"train": (test_cameras(cfg.n_train, src.radius, cfg.train_rings_deg)
                      if cfg.train_rings_deg else
                      train_cameras(cfg.n_train, src.radius, rng, cfg.train_elevation_deg)),
            "test": test_cameras(cfg.n_test, src.radius, cfg.test_elevations_deg)}
    out = Path(cfg.out_dir)
    relight_names = [p.stem for p in src.relight]
    for sub in ["train", "test", *(f"test_relight/{n}" for n in relight_names)]:
        (out / sub).mkdir(parents=True, exist_ok=True)
    spp_test = cfg.spp_test or 2 * cfg.spp
    renderer = sio.Renderer(_scene_spec(cfg, src), src.env_bitmaps[src.env_path])
    train_images = _render_views(renderer, cams, cfg, out, spp_test, progress)
    if cfg.sfm_points > 0:
        pts, cols = sample_visible_points(renderer.scene, cams["train"], train_images, cfg.fov_deg,
                                          int(cfg.sfm_points), np.random.default_rng(cfg.seed + 17),
                                          radius=src.bound_r)
        write_points_ply(out / "points3d.ply", pts, cols)
    _render_relit(renderer, cams["test"], src, cfg, out, spp_test, progress)
    angle_x = float(np.radians(cfg.fov_deg))
    for split in ("train", "test"):
        _write_json(out / f"transforms_{split}.json", {
            "camera_angle_x": angle_x, "w": cfg.resolution, "h": cfg.resolution,
            "frames": [_frame_json(c) for c in cams[split]]})
    seconds = time.perf_counter() - t0
    meta = _meta(cfg, src.mesh_path, src.env_path, src.relight, src.texture, src.obj_m,
                 src.bound_r, src.radius, src.raw, src.variant, spp_test, seconds)
    _write_json(out / "meta.json", meta)
    return {"out_dir": str(out), "n_train": cfg.n_train, "n_test": len(cams["test"]),
            "relight": relight_names, "radius": src.radius, "resolution": cfg.resolution,
            "seconds": seconds, "variant": src.variant}


@dataclass
class _ObjectInputs:
    """The checked inputs of one object dataset: files, loaded maps and mesh, framing."""
    mesh_path: Path
    env_path: Path
    relight: list[Path]
    variant: str
    env_bitmaps: dict              # {map path: mi.Bitmap}, the lighting map and relit ones
    raw: dict                      # sio.load_mesh of the mesh file
    obj_m: np.ndarray              # [4, 4] mesh file -> world
    bound_r: float                 # bounding-sphere radius in world units
    texture: Path | None
    radius: float                  # camera distance from the origin


def _object_inputs(cfg: ObjectDatasetConfig) -> _ObjectInputs:
    """Find and load every input (FileNotFoundError / ValueError before any rendering) and
    frame the object: the camera radius fits its bounding sphere into the field of view."""
    if cfg.mesh is not None and str(cfg.mesh) == BUILTIN_DETAIL_MESH:   # procedural stress object
        mesh_path = write_detail_mesh(Path(cfg.out_dir) / "source")
    else:
        mesh_path = Path(cfg.mesh) if cfg.mesh is not None else default_mesh()
    env_path = Path(cfg.envmap) if cfg.envmap is not None else default_envmap()
    if not mesh_path.is_file():
        raise FileNotFoundError(f"mesh file not found: {mesh_path}")
    if not env_path.is_file():
        raise FileNotFoundError(f"environment map not found: {env_path}")
    relight = _relight_paths(cfg.relight_envmaps)
    variant = sio.activate_variant(cfg.variant)
    env_bitmaps = {p: load_envmap(p) for p in [env_path, *relight]}  # validate all first
    raw = sio.load_mesh(mesh_path)
    obj_m, bound_r = object_transform(raw["vertices"], cfg.up_axis, cfg.half_extent)
    texture = _texture(cfg.texture, mesh_path, raw["has_uv"])
    half_fov = np.radians(cfg.fov_deg) / 2
    radius = float(cfg.radius) if cfg.radius is not None else \
        float(cfg.radius_margin * bound_r / np.sin(half_fov))
    if radius <= bound_r:
        warnings.warn(f"camera radius {radius:.3f} is inside the object's bounding sphere "
                      f"({bound_r:.3f}); views may clip the object")
    return _ObjectInputs(mesh_path, env_path, relight, variant, env_bitmaps, raw, obj_m,
                         bound_r, texture, radius)


def _scene_spec(cfg: ObjectDatasetConfig, src: _ObjectInputs) -> sio.SceneSpec:
    return sio.SceneSpec(mesh=src.mesh_path, object_to_world=src.obj_m, texture=src.texture,
                         base_color=cfg.base_color, roughness=cfg.roughness,
                         metallic=cfg.metallic, resolution=cfg.resolution, fov_deg=cfg.fov_deg,
                         max_depth=cfg.max_depth, envmap_to_world=ENVMAP_TO_WORLD,
                         envmap_scale=cfg.envmap_scale)


def render_seed(seed: int, i: int, kind: int) -> int:
    """Sampler seed of render ``i`` of one ``kind`` (distinct noise per render): kind 0 train,
    1 test, 2 AOV, 3 + k relit under map k (the composition dataset: 2 composites)."""
    return (int(seed) * 1_000_003 + 256 * i + kind) % 2**32


def _render_views(renderer, cams: dict, cfg: ObjectDatasetConfig, out: Path, spp_test: int,
                  progress: bool) -> list:
    """Write the train and test views (test: + linear EXR and the G-buffer ground truth);
    fills each camera's file paths; returns the train renders when SfM points are asked for."""
    train_images = []
    for split, spp in (("train", cfg.spp), ("test", spp_test)):
        for i, cam in enumerate(_bar(cams[split], f"{split} views", progress)):
            rgba = renderer.radiance(cam["to_world_mitsuba"], spp,
                                     render_seed(cfg.seed, i, int(split == "test")))
            if split == "train" and cfg.sfm_points > 0:
                train_images.append(rgba)
            cam["file_path"] = f"./{split}/r_{i}"
            sio.write_png(out / f"{split}/r_{i}.png", rgba)
            if split == "test":
                sio.write_exr(out / f"test/r_{i}.exr", rgba)
                gt = renderer.gbuffer(cam["to_world_mitsuba"], cfg.spp_aov,
                                      render_seed(cfg.seed, i, 2))
                for key in ("albedo", "normal", "depth"):
                    sio.write_exr(out / f"test/r_{i}_{key}.exr", gt[key])
                    cam[f"{key}_path"] = f"./test/r_{i}_{key}.exr"
                cam["radiance_path"] = f"./test/r_{i}.exr"
    return train_images


def _render_relit(renderer, test_cams: list, src: _ObjectInputs, cfg: ObjectDatasetConfig,
                  out: Path, spp_test: int, progress: bool) -> None:
    """The test views under each held-out map (``test_relight/<map>/``)."""
    for k, path in enumerate(src.relight):
        name = path.stem
        renderer.set_envmap(src.env_bitmaps[path])
        for i, cam in enumerate(_bar(test_cams, f"relight {name}", progress)):
            rgba = renderer.radiance(cam["to_world_mitsuba"], spp_test,
                                     render_seed(cfg.seed, i, 3 + k))
            stem = out / f"test_relight/{name}/r_{i}"
            sio.write_png(stem.with_suffix(".png"), rgba)
            sio.write_exr(stem.with_suffix(".exr"), rgba)
            cam.setdefault("relight", {})[name] = f"./test_relight/{name}/r_{i}"


def _relight_paths(maps) -> list[Path]:
    """Existing files, or names of shared maps (``"venice_sunset_1k.hdr"``)."""
    if maps is None:
        paths = [shared_envmap(n) for n in HELDOUT_ENVMAPS]
        return paths if all(p.is_file() for p in paths) else []
    paths = []
    for m in maps:
        p = Path(m)
        if not p.is_file() and str(m) in TRAIN_ENVMAPS + HELDOUT_ENVMAPS:
            p = shared_envmap(str(m))
        if not p.is_file():
            raise FileNotFoundError(f"relighting envmap not found: {p}")
        paths.append(p)
    if len({p.stem for p in paths}) != len(paths):
        raise ValueError(f"relighting envmaps need distinct file names: {[str(p) for p in paths]}")
    return paths


def _texture(setting, mesh_path: Path, has_uv: bool) -> Path | None:
    if setting is None:
        return None
    tex = find_texture(mesh_path) if setting == "auto" else Path(setting)
    if tex is not None and not tex.is_file():
        raise FileNotFoundError(f"texture file not found: {tex}")
    if tex is not None and not has_uv:
        warnings.warn(f"{mesh_path} has no texture coordinates; ignoring texture {tex}")
        return None
    return tex


def _bar(items, desc, enabled):
    if not enabled:
        return items
    return tqdm(items, desc=desc, unit="view", leave=False)


def _frame_json(cam: dict) -> dict:
    d = {"file_path": cam["file_path"],
         "transform_matrix": (cam["transform_matrix"] + 0.0).tolist(),  # + 0.0: no -0.0
         "to_world_mitsuba": (cam["to_world_mitsuba"] + 0.0).tolist(),
         "elevation_deg": cam["elevation_deg"], "azimuth_deg": cam["azimuth_deg"]}
    for key in ("radiance_path", "albedo_path", "normal_path", "depth_path", "relight"):
        if key in cam:
            d[key] = cam[key]
    return d


def _meta(cfg, mesh_path, env_path, relight, texture, obj_m, bound_r, radius, raw,
          variant, spp_test, seconds) -> dict:
    return {
        "generator": GENERATOR_VERSION, "comgs_dr_version": package_version(),
        "mitsuba_version": mi.__version__, "variant": variant, "seconds": round(seconds, 2),
        "mesh": str(mesh_path.resolve()), "texture": str(texture.resolve()) if texture else None,
        "envmap": str(env_path.resolve()), "envmap_scale": cfg.envmap_scale,
        "relight_envmaps": {p.stem: str(p.resolve()) for p in relight},
        "train_envmaps": list(TRAIN_ENVMAPS), "heldout_envmaps": list(HELDOUT_ENVMAPS),
        "envmap_orientation": {
            "to_world_mitsuba": ENVMAP_TO_WORLD.tolist(),
            "mapping": "world dir d -> u = 0.5 - atan2(d_y, d_x)/(2 pi), v = acos(d_z)/pi "
                       "(v=0 top row; Blender's Z-up equirect convention)"},
        "object": {
            "up_axis_in_file": cfg.up_axis,
            "object_to_world": obj_m.tolist(),
            "note": "world = object_to_world @ mesh-file point: centre bbox, "
                    + ("rotate +90 deg about X (+Y up -> +Z up), " if cfg.up_axis == "y" else "")
                    + f"scale largest half side to {cfg.half_extent}",
            "bbox_in_file": [raw["vertices"].min(0).tolist(), raw["vertices"].max(0).tolist()],
            "bounding_radius": bound_r},
        "material": {"bsdf": "principled", "base_color": "texture" if texture else
                     list(cfg.base_color), "roughness": cfg.roughness, "metallic": cfg.metallic,
                     "specular": 0.5},
        "cameras": {"radius": radius, "fov_deg": cfg.fov_deg, "look_at": [0, 0, 0],
                    "up": [0, 0, 1], "train": "uniform on the zone elevation "
                    f"{list(cfg.train_elevation_deg)} deg", "test_elevations_deg":
                    list(cfg.test_elevations_deg), "seed": cfg.seed,
                    "transform_matrix": "NeRF/Blender camera-to-world (OpenGL: looks down -Z, "
                    "+Y up); to_world_mitsuba = transform_matrix @ diag(-1,1,-1,1)",
                    "near_far_hint": [max(radius - bound_r, 1e-3), radius + bound_r]},
        "render": {"integrator": "path", "max_depth": cfg.max_depth, "hide_emitters": True,
                   "rfilter": "box", "spp_train": cfg.spp, "spp_test": spp_test,
                   "spp_aov": cfg.spp_aov, "resolution": [cfg.resolution, cfg.resolution]},
        "colour_space": {
            "png": "8-bit sRGB-encoded (IEC 61966-2-1) linear radiance, clipped to [0,1], "
                   "straight (non-premultiplied) alpha = box-filtered pixel coverage",
            "radiance_exr": "linear HDR RGB premultiplied by alpha (OpenEXR convention)",
            "albedo_exr": "linear RGB diffuse reflectance (Mitsuba 'albedo' AOV), "
                          "averaged over covered samples; A = coverage",
            "normal_exr": "world-space shading normal (R,G,B = X,Y,Z), average over "
                          "covered samples renormalised to unit length; 0 where uncovered; "
                          "A = coverage",
            "depth_exr": "Y = distance along the unit-length ray (not z-depth), averaged "
                         "over covered samples; 0 where uncovered",
            "background": "transparent: the environment is not visible to camera rays"},
    }


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2))
