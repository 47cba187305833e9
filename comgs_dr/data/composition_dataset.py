"""Path-traced ground truth for object-into-scene composition (``comgs make-dataset composition``).

A scene (a large photo-textured ground, a brick wall and a box; principled two-sided BSDFs)
is lit by the scene map; each object is captured alone under a different map; then the
objects are placed ON the ground, close enough for one to shadow the other, and the real
composite is path-traced (shadows, inter-reflections) beside the same view without objects::

    scene/             NeRF-synthetic capture of the scene WITHOUT the objects: opaque RGB PNGs
                       (the ground fills the frames), transforms_{train,test}.json, points3d.ply
    objects/<name>/    the object alone, transparent background (``make_object_dataset`` format)
    transform.json     placements {name: {"transform": 16 floats}} (``core.similarity``):
                       object capture world (normalised frame) -> scene world
    comp/transforms_test.json   spiral test cameras around the placement centre
    comp/{gt,empty}/r_<i>.png   composite with the objects / the same view without them
                       (opaque 8-bit sRGB; .exr beside: linear HDR RGBA, alpha = 1)
    comp/mask/r_<i>.png         8-bit coverage of the objects in the composite (visible part)
    assets/*.png       the ground and wall textures; composition.json: metadata

World: Z-up, ground top at z = 0. Env maps use ``synthetic.ENVMAP_TO_WORLD`` (Blender's Z-up
equirect), in the scene and in the object captures. A placed mesh's Mitsuba ``to_world`` is
``placement @ object_to_world`` (the latter from ``objects/<name>/meta.json``). The gt and
empty frames of one view share their random seed (correlated noise: their difference is the
objects' effect).
"""
from __future__ import annotations

import dataclasses
import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from comgs_dr.core.colorspace import LUMA, srgb_encode
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.similarity import Similarity, write_placements
from comgs_dr.core.variant import package_version
from comgs_dr.data import synthetic as syn
from comgs_dr.data import synthetic_io as sio
from comgs_dr.data.images import write_png8
from comgs_dr.data.sfm_points import sample_visible_points, write_points_ply
from comgs_dr.lighting.envmap import load_envmap

GENERATOR_VERSION = "comgs_dr.data.composition_dataset/1"
#: Named objects of the shared data: mesh (relative to the data dir) and known material.
SHARED_OBJECTS = {
    "spot": {"mesh": "meshes/spot_triangulated.obj", "texture": "auto",
             "base_color": (0.6, 0.6, 0.6), "roughness": 0.5, "metallic": 0.0},
    "teapot": {"mesh": "meshes/teapot.obj", "texture": None,
               "base_color": (0.8, 0.3, 0.08), "roughness": 0.25, "metallic": 0.0},
    "suzanne": {"mesh": "meshes/suzanne.obj", "texture": None,
                "base_color": (0.9, 0.7, 0.35), "roughness": 0.3, "metallic": 1.0},
}
PATH_OBJECT = {"texture": "auto", "base_color": (0.6, 0.6, 0.6), "roughness": 0.5, "metallic": 0.0}
GROUND_HALF = 25.0           # ground: a 50 x 50 square, top at z = 0
GROUND_TILE = 2.0            # one texture tile per 2 x 2 units
GROUND_TINT = (0.85, 0.75, 0.6)   # sRGB multipliers of the gravel: a warm grey ground
MESH_SUFFIXES = (".obj", ".ply")
PROBE_MAX_HEIGHT = 4096      # rows of a placement probe (= data.placement_probe.MAX_HEIGHT)


@dataclass
class CompositionDatasetConfig:
    """Settings of :func:`make_composition_dataset` (defaults: a few minutes on 2 CPU cores).

    ``objects``: names of :data:`SHARED_OBJECTS` or .obj/.ply paths (Y-up files), or one
    comma-separated string of them. Maps: names of shared HDRIs (``hdri/<name>``) or paths.
    ``resolution``: side of the captures in pixels; ``comp_resolution``: of the composites
    (None: ``resolution``; the evaluation may look closer than the captures). ``test_views``
    sizes the test split of the scene, of each object and of ``comp/``. Training views use
    ``spp`` samples per pixel, test views and composites ``spp_test`` (None: 2 * spp).
    ``object_scale``: world half size of each placed object's largest side; ``spacing``:
    centre distance of neighbours in object sizes. Angles in degrees, lengths in scene units
    (the ground is ``2 * ground_half`` wide).

    ``probe_height``: rows of ``probes/<object>.exr``, the true light at the centre of each
    object's box, which ``comgs make-dataset composition`` path-traces after the dataset
    (``data.placement_probe.write_probes``; this function writes none); 0: none.

    Example: ``CompositionDatasetConfig(out_dir="comp", objects="spot,teapot", resolution=64)``.
    """
    out_dir: str | Path = "composition"
    objects: tuple[str, ...] = ("spot", "teapot")
    scene_map: str | Path = "blender_sunrise.exr"
    object_map: str | Path = "blender_studio.exr"
    resolution: int = 96
    comp_resolution: int | None = None
    scene_views: int = 64
    object_views: int = 48
    test_views: int = 8
    spp: int = 128
    spp_test: int | None = None
    max_depth: int = 8
    seed: int = 0
    fov_deg: float = 40.0
    object_scale: float = 0.5
    spacing: float = 1.5
    sfm_points: int = 10000          # 0: no scene/points3d.ply
    scene_envmap_scale: float = 1.0
    object_envmap_scale: float = 1.0
    variant: str | None = None       # None: keep the active JIT variant
    #: material of objects given as mesh paths (keys of PATH_OBJECT: texture, base_color,
    #: roughness, metallic); None: PATH_OBJECT (grey, the mesh's texture if any)
    path_material: dict | None = None
    #: elevation range of the scene's training cameras (degrees above the ground); low
    #: elevations see the horizon and the sky, as a capture at eye level does
    scene_elevation_deg: tuple[float, float] = (30.0, 70.0)
    #: half side of the square ground; beyond it low cameras see the map's own horizon
    ground_half: float = GROUND_HALF
    #: sRGB multipliers of the ground's gravel texture (``write_textures``): a brighter
    #: ground (a stress case for lighting that infers the sky from what the ground reflects)
    ground_tint: tuple[float, float, float] = GROUND_TINT
    #: extra training views from eye height that look out over the horizon (a capture that
    #: turns around): they see the sky and the sun, which step 1's background learns
    sky_views: int = 0
    sky_pitch_deg: tuple[float, float] = (5.0, 30.0)
    #: the first sky view faces the sun's azimuth (pitch: the sun's elevation clamped to
    #: ``sky_pitch_deg``), so the capture sees the sun whenever it is low enough; otherwise
    #: the stratified random azimuths can miss a low sun altogether
    sun_view: bool = False
    probe_height: int = 128

    def __post_init__(self):
        if isinstance(self.objects, str):
            self.objects = tuple(o.strip() for o in self.objects.split(",") if o.strip())
        self.objects = tuple(str(o) for o in self.objects)
        if not self.objects:
            raise ValueError("CompositionDatasetConfig.objects must name >= 1 object")
        for o in self.objects:
            if o not in SHARED_OBJECTS and Path(o).suffix.lower() not in MESH_SUFFIXES:
                raise ValueError(f"unknown object {o!r}: use one of {', '.join(SHARED_OBJECTS)} "
                                 "or a path to an .obj/.ply mesh")
        bounds = {"scene_views": 1, "object_views": 1, "test_views": 1, "spp": 1, "max_depth": 1,
                  "resolution": 8, "sfm_points": 0, "spp_test": 1, "sky_views": 0,
                  "comp_resolution": 8}
        for name, lo in bounds.items():
            v = getattr(self, name)
            if v is not None and int(v) < lo:
                raise ValueError(f"CompositionDatasetConfig.{name} must be >= {lo} (got {v})")
        for name in ("object_scale", "spacing", "scene_envmap_scale", "object_envmap_scale",
                     "ground_half"):
            if not float(v := getattr(self, name)) > 0:
                raise ValueError(f"CompositionDatasetConfig.{name} must be > 0 (got {v})")
        tint = np.asarray(self.ground_tint, np.float64)
        if tint.shape != (3,) or not (np.isfinite(tint).all() and (tint > 0).all()):
            raise ValueError(f"CompositionDatasetConfig.ground_tint must be 3 finite values "
                             f"> 0, got {self.ground_tint!r}")
        self.ground_tint = tuple(float(t) for t in tint)
        bad = set(self.path_material or {}) - set(PATH_OBJECT)
        if bad:
            raise ValueError(f"CompositionDatasetConfig.path_material: unknown keys {sorted(bad)} "
                             f"(allowed: {', '.join(PATH_OBJECT)})")
        if not 1.0 < float(self.fov_deg) < 120.0:
            raise ValueError(f"CompositionDatasetConfig.fov_deg must be in (1, 120) (got {self.fov_deg})")
        if not 0 <= int(self.probe_height) <= PROBE_MAX_HEIGHT:
            raise ValueError(f"CompositionDatasetConfig.probe_height must be in "
                             f"[0, {PROBE_MAX_HEIGHT}], got {self.probe_height}")


# ----------------------------------------------------------------------------- inputs

def resolve_map(m) -> Path:
    """A shared HDRI name (``blender_sunrise.exr``) or an existing path; FileNotFoundError."""
    for p in (Path(m), syn.shared_data_dir() / "hdri" / str(m)):
        if p.is_file():
            return p
    avail = sorted(x.name for x in (syn.shared_data_dir() / "hdri").glob("*"))   # [] if absent
    raise FileNotFoundError(f"environment map not found: {m!r} (neither a file nor a shared map; "
                            f"shared maps: {', '.join(avail) or 'none found'})")


def resolve_objects(names, path_material: dict | None = None) -> dict[str, dict]:
    """{name: {mesh: Path, texture, base_color, roughness, metallic}} for names or paths
    (mesh files get :data:`PATH_OBJECT` updated by ``path_material``)."""
    out = {}
    path_spec = {**PATH_OBJECT, **(path_material or {})}
    for o in names:
        spec, name = ((dict(SHARED_OBJECTS[o], mesh=syn.shared_data_dir() / SHARED_OBJECTS[o]["mesh"]), o)
                      if o in SHARED_OBJECTS else (dict(path_spec, mesh=Path(o)), Path(o).stem))
        if not spec["mesh"].is_file():
            raise FileNotFoundError(f"mesh of object {o!r} not found: {spec['mesh']}")
        if name in out:
            raise ValueError(f"two objects are named {name!r}; object names must be distinct")
        out[name] = spec
    return out


def sun_direction(bitmap) -> np.ndarray:
    """[3] unit world direction of the brightest texel (Z-up equirect, ENVMAP_TO_WORLD)."""
    a = np.array(bitmap, np.float32)[..., :3]                      # [H, W, 3]
    h, w = a.shape[:2]
    i, j = np.unravel_index(np.argmax(a @ LUMA), (h, w))
    th, phi = np.pi * (i + 0.5) / h, 2 * np.pi * (0.5 - (j + 0.5) / w)
    return np.array([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)])


def write_textures(folder: Path, ground_tint=GROUND_TINT) -> dict[str, Path]:
    """Photo textures of scikit-image as sRGB PNGs: tinted gravel (ground), brick (wall).
    ``ground_tint``: sRGB multipliers of the gravel's (0.25 + 0.7 g) pattern, clipped to 1
    (the default's linear mean is about 0.2; (1.25, 1.25, 1.2) gives a pale, sand- or
    concrete-like ground near 0.45)."""
    from skimage import data
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for key, img, tint in (("ground", data.gravel(), tuple(ground_tint)),
                           ("wall", data.brick(), (0.85, 0.5, 0.4))):
        g = img.astype(np.float32)[..., None] / 255.0                    # [H, W, 1]
        out[key] = folder / f"{key}.png"
        write_png8(out[key], np.clip((0.25 + 0.7 * g) * np.array(tint), 0.0, 1.0))
    return out


# ----------------------------------------------------------------------------- layout

def rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def scene_layout(az: float, clear: float, ground_half: float = GROUND_HALF) -> dict:
    """Shapes of the scene for sun azimuth ``az`` (deg) and objects within ``clear`` of the
    origin: the ground (top at z = 0), a brick wall on the side away from the sun (lit, it
    reflects onto the objects), a box to the side; {name: {type, to_world [4, 4], texture key
    or base_color, roughness, uv_repeat}}."""
    u = syn._direction(0.0, az)                                        # [3] towards the sun
    v = np.cross([0.0, 0.0, 1.0], u)
    rep = 2 * ground_half / GROUND_TILE
    shapes = {"ground": {"type": "rectangle", "to_world": np.diag([ground_half] * 2 + [1.0, 1.0]),
                         "texture": "ground", "roughness": 0.8, "uv_repeat": [rep, rep]},
              "wall": {"type": "cube", "texture": "wall", "roughness": 0.7, "uv_repeat": [3.0, 1.0]},
              "box": {"type": "cube", "base_color": [0.25, 0.45, 0.3], "roughness": 0.4}}
    for key, centre, half, yaw in (("wall", -(clear + 1.1) * u, (0.1, 2.5, 0.7), az),
                                   ("box", (clear + 0.9) * v, (0.35, 0.35, 0.35), az + 25.0)):
        m = np.eye(4)
        m[:3, :3] = rot_z(yaw) @ np.diag(half)                     # cube [-1, 1]^3
        m[:3, 3] = centre + [0.0, 0.0, half[2]]                    # resting on the ground
        shapes[key]["to_world"] = m
    return shapes


def sky_cameras(n: int, radius: float, rng: np.random.Generator,
                pitch_deg=(5.0, 30.0), height: float = 0.6, aim_deg=None) -> list[dict]:
    """``n`` cameras at ``height`` on the circle of ``radius`` (the scene cameras' ring, outside
    the wall and the box), each looking outwards (away from the centre) and ``pitch_deg``
    above the horizon; azimuths and pitches stratified so that together they sweep the
    whole horizon. ``aim_deg`` (azimuth, elevation): the first camera looks that way (its
    elevation clamped to ``pitch_deg``), the others keep their strata around it."""
    azs = (np.arange(n) + rng.uniform(0, 1, n)) * 360.0 / max(n, 1)
    pitches = rng.permutation(np.linspace(*pitch_deg, max(n, 1)))
    if aim_deg is not None and n > 0:
        azs = azs - azs[0] + float(aim_deg[0])
        pitches[0] = float(np.clip(aim_deg[1], *pitch_deg))
    out = []
    for k, (a, p) in enumerate(zip(azs, pitches)):
        o = radius * syn._direction(0.0, a) + [0.0, 0.0, height]
        m = syn.look_at(o, o + syn._direction(p, a))
        out.append({"elevation_deg": float(p), "azimuth_deg": float(a % 360.0),
                    "to_world_mitsuba": m, "transform_matrix": m @ syn.GL_FROM_MITSUBA})
    return out


def place_objects(norm_verts: dict[str, np.ndarray], sun_az_deg: float, scale: float,
                  spacing: float, rng: np.random.Generator) -> dict[str, Similarity]:
    """Similarities capture world -> scene world: uniform ``scale``, a random rotation about Z,
    objects on a line 10 deg off the sun azimuth (the first nearest the sun, so it shadows
    the next), ``spacing * 2 * scale`` apart, each lowest point on the ground (z = 0).
    ``norm_verts``: {name: [N, 3] vertices in the capture (normalised) frame}."""
    u = syn._direction(0.0, sun_az_deg + 10.0)
    n, step = len(norm_verts), spacing * 2.0 * scale
    out, radii = {}, []
    for k, (name, v) in enumerate(norm_verts.items()):
        rot = rot_z(float(rng.uniform(0.0, 360.0)))
        t = ((n - 1) / 2.0 - k) * step * u
        t[2] = -scale * v[:, 2].min()
        out[name] = Similarity(float(scale), rot, t)
        radii.append(scale * np.linalg.norm(v[:, :2], axis=1).max())
    for k in range(n - 1):
        if radii[k] + radii[k + 1] > step:
            raise ValueError(f"spacing {spacing} is too small: objects {k} and {k + 1} may "
                             f"intersect (need >= {(radii[k] + radii[k + 1]) / (2 * scale):.3f})")
    return out


# ----------------------------------------------------------------------------- rendering

def scene_dict(cfg, env_bitmap, textures: dict, layout: dict, objects: dict | None = None) -> dict:
    """Mitsuba scene: path tracer with the env map visible, the layout's shapes (two-sided
    principled), ``objects`` ({name: sio.SceneSpec with the placed to_world}), one sensor."""
    T = mi.ScalarTransform4f
    d = {"type": "scene",
         "integrator": {"type": "path", "max_depth": int(cfg.max_depth), "hide_emitters": False},
         "env": {"type": "envmap", "bitmap": env_bitmap, "scale": float(cfg.scene_envmap_scale),
                 "to_world": T(syn.ENVMAP_TO_WORLD.tolist())},
         "sensor": {"type": "perspective", "fov": float(cfg.fov_deg), "fov_axis": "x",
                    "film": {"type": "hdrfilm", "width": int(cfg.resolution),
                             "height": int(cfg.resolution), "pixel_format": "rgba",
                             "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": 1}}}
    for key, sh in layout.items():
        base = ({"type": "bitmap", "filename": str(textures[sh["texture"]]),
                 "to_uv": mi.ScalarTransform3f().scale(sh["uv_repeat"])} if sh.get("texture")
                else {"type": "rgb", "value": sh["base_color"]})
        d[key] = {"type": sh["type"], "to_world": T(sh["to_world"].tolist()),
                  "bsdf": {"type": "twosided", "material": {
                      "type": "principled", "base_color": base, "roughness": sh["roughness"]}}}
    for name, spec in (objects or {}).items():
        d[f"object_{name}"] = sio.scene_dict(spec, None)["object"]   # same mesh + BSDF as the capture
    return d


class SceneRenderer(sio.Renderer):
    """:class:`synthetic_io.Renderer` over any scene dict (radiance + object coverage)."""

    def __init__(self, scene: dict):           # no AOV integrator / env swapping needed
        self.scene = mi.load_dict(scene)
        self.sensor = self.scene.sensors()[0]
        self._params = mi.traverse(self.sensor)

    def coverage(self, to_world, prefix: str = "object_", ss: int = 4) -> np.ndarray:
        """[H, W] fraction of ss x ss sub-pixel rays whose first hit is a shape ``prefix*``."""
        self._place(to_world)
        shapes = [s for s in self.scene.shapes() if s.id().startswith(prefix)]
        w, h = self.sensor.film().crop_size()
        iy, ix, sy, sx = np.meshgrid(np.arange(h), np.arange(w), np.arange(ss), np.arange(ss),
                                     indexing="ij")
        pos = to_jit(mi.Point2f, np.stack([((ix + (sx + 0.5) / ss) / w).ravel(),
                                           ((iy + (sy + 0.5) / ss) / h).ravel()]))
        ray, _ = self.sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
        si = self.scene.ray_intersect(ray)
        hit = np.zeros(w * h * ss * ss, bool)
        for s in shapes:
            hit |= np.array(si.shape == mi.ShapePtr(s), bool)
        return hit.reshape(h, w, ss * ss).mean(-1, dtype=np.float32)


def write_opaque(stem: Path, rgba: np.ndarray, exr: bool = False) -> None:
    """Opaque 8-bit sRGB PNG of linear radiance (clipped to [0, 1]); ``exr``: linear RGBA too."""
    write_png8(stem.with_suffix(".png"), srgb_encode(np.clip(rgba[..., :3], 0.0, 1.0)))
    if exr:
        sio.write_exr(stem.with_suffix(".exr"), rgba)


def spiral_cameras(n: int, centre, radius: float, elevation_deg=(30.0, 60.0),
                   turns: float = 1.0, azimuth0_deg: float = 0.0) -> list[dict]:
    """``n`` cameras on a spiral around ``centre``: elevation rising linearly, ``turns``
    full turns in azimuth, all looking at ``centre`` (Z up)."""
    out = []
    for i in range(n):
        e = elevation_deg[0] + i / max(n - 1, 1) * (elevation_deg[1] - elevation_deg[0])
        a = azimuth0_deg + 360.0 * turns * i / n
        m = syn.look_at(np.asarray(centre) + radius * syn._direction(e, a), centre)
        out.append({"elevation_deg": float(e), "azimuth_deg": float(a % 360.0),
                    "to_world_mitsuba": m, "transform_matrix": m @ syn.GL_FROM_MITSUBA})
    return out


# ----------------------------------------------------------------------------- driver

def make_composition_dataset(cfg: CompositionDatasetConfig, progress: bool = True) -> dict:
    """Render the composition dataset into ``cfg.out_dir`` (see the module docstring).

    Returns a summary (out_dir, objects, counts, resolution, seconds per part, variant).
    Raises FileNotFoundError for missing maps/meshes, ValueError for invalid settings;
    both before anything is written.
    """
    t0 = time.perf_counter()
    cfg = dataclasses.replace(cfg)                       # re-validates
    src = _inputs(cfg)
    out, spp_test = Path(cfg.out_dir), int(cfg.spp_test or 2 * cfg.spp)
    rng = np.random.default_rng(cfg.seed)
    geo = _arrangement(cfg, src, rng)
    textures = write_textures(out / "assets", cfg.ground_tint)
    seconds = {}
    t = time.perf_counter()
    empty = _render_scene(cfg, src, geo, textures, rng, out, spp_test, progress)
    seconds["scene"] = time.perf_counter() - t
    seconds["objects"] = _render_objects(cfg, src, out, spp_test, progress)
    write_placements(out / "transform.json", geo.placements)
    t = time.perf_counter()
    specs, ccfg = _render_composites(cfg, src, geo, textures, empty, out, spp_test, progress)
    seconds["comp"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t0
    meta = _metadata(cfg, ccfg, src, geo, specs, spp_test, seconds)
    (out / "composition.json").write_text(json.dumps(meta, indent=2))
    return {"out_dir": str(out), "objects": list(src.objects),
            "n_scene_train": cfg.scene_views + cfg.sky_views, "n_test": cfg.test_views, "n_object_train": cfg.object_views,
            "resolution": cfg.resolution, "comp_resolution": ccfg.resolution, "seconds": seconds,
            "variant": src.variant}


@dataclass
class _Inputs:
    """The checked inputs: map files, the scene map loaded, the objects' specs, the variant."""
    scene_map: Path
    object_map: Path
    objects: dict                   # resolve_objects; object_to_world and texture filled later
    variant: str
    env: object                     # the scene map as an mi.Bitmap


@dataclass
class _Arrangement:
    """Where everything stands: the sun, the objects' placements and boxes, camera radii and
    the scene's shapes (all in the scene world, Z-up)."""
    sun: np.ndarray                 # [3] unit direction of the brightest texel
    az: float                       # its azimuth in degrees (0 when it is at the zenith)
    placements: dict                # {name: Similarity} capture world -> scene world
    bbox: dict                      # {name: ([3] min, [3] max)} placed object's world box
    centre: np.ndarray              # [3] centre of the objects' joint box
    comp_radius: float              # distance of the composite cameras from the centre
    scene_radius: float             # distance of the scene capture's cameras from the origin
    layout: dict                    # scene_layout: ground, wall, box


def _inputs(cfg: CompositionDatasetConfig) -> _Inputs:
    """Resolve and load maps and meshes (errors before anything is written)."""
    scene_map, object_map = resolve_map(cfg.scene_map), resolve_map(cfg.object_map)
    objects = resolve_objects(cfg.objects, cfg.path_material)
    variant = sio.activate_variant(cfg.variant)
    env = load_envmap(scene_map)
    with warnings.catch_warnings():                      # validate before rendering;
        warnings.simplefilter("ignore")                  # the object run warns itself
        load_envmap(object_map)
    return _Inputs(scene_map, object_map, objects, variant, env)


def _arrangement(cfg: CompositionDatasetConfig, src: _Inputs, rng) -> _Arrangement:
    """Place the objects near the origin in line with the sun (each object's
    ``object_to_world`` is filled in ``src.objects``), and size the camera rings so the
    composites frame the group and the scene capture sees around it."""
    sun = sun_direction(src.env)
    az = float(np.degrees(np.arctan2(sun[1], sun[0]))) if np.hypot(*sun[:2]) > 1e-6 else 0.0
    norm = {}                                            # {name: [N, 3] capture-frame vertices}
    for name, o in src.objects.items():
        v = sio.load_mesh(o["mesh"])["vertices"]
        o["object_to_world"], _ = syn.object_transform(v, "y", 1.0)
        norm[name] = v @ o["object_to_world"][:3, :3].T + o["object_to_world"][:3, 3]
    placements = place_objects(norm, az, cfg.object_scale, cfg.spacing, rng)
    bbox = {n: (lambda w: (w.min(0), w.max(0)))(placements[n].points(norm[n])) for n in src.objects}
    centre = (np.min([b[0] for b in bbox.values()], 0) + np.max([b[1] for b in bbox.values()], 0)) / 2
    group_r = max(np.linalg.norm(p.translation[:2]) for p in placements.values()) \
        + np.sqrt(2) * cfg.object_scale                  # horizontal radius of the group
    comp_radius = float(1.1 * group_r / np.sin(np.radians(cfg.fov_deg) / 2))
    scene_radius = 1.25 * comp_radius
    layout = scene_layout(az, group_r, float(cfg.ground_half))
    return _Arrangement(sun, az, placements, bbox, centre, comp_radius, scene_radius, layout)


def _render_scene(cfg, src: _Inputs, geo: _Arrangement, textures: dict, rng, out: Path,
                  spp_test: int, progress: bool) -> "SceneRenderer":
    """``scene/``: the capture of the scene without the objects (orbit views, optional sky
    views, test views, SfM points); returns its renderer for the empty composites."""
    sun_elevation = float(np.degrees(np.arcsin(np.clip(geo.sun[2], -1, 1))))
    aim = (geo.az, sun_elevation) if cfg.sun_view else None
    cams = {"train": syn.train_cameras(cfg.scene_views, geo.scene_radius, rng,
                                       tuple(cfg.scene_elevation_deg))
            + sky_cameras(cfg.sky_views, geo.scene_radius, rng, tuple(cfg.sky_pitch_deg),
                          aim_deg=aim),
            "test": syn.test_cameras(cfg.test_views, geo.scene_radius, (35.0, 55.0))}
    empty = SceneRenderer(scene_dict(cfg, src.env, textures, geo.layout))
    images = []
    for split, spp in (("train", cfg.spp), ("test", spp_test)):
        (out / "scene" / split).mkdir(parents=True, exist_ok=True)
        for i, cam in enumerate(syn._bar(cams[split], f"scene {split}", progress)):
            rgba = empty.radiance(cam["to_world_mitsuba"], spp,
                                  syn.render_seed(cfg.seed, i, split == "test"))
            images += [rgba] if split == "train" else []
            cam["file_path"] = f"./{split}/r_{i}"
            write_opaque(out / "scene" / split / f"r_{i}", rgba)
    if cfg.sfm_points:
        pts, cols = sample_visible_points(empty.scene, cams["train"], images, cfg.fov_deg,
                                          int(cfg.sfm_points), np.random.default_rng(cfg.seed + 17),
                                          radius=geo.scene_radius)
        write_points_ply(out / "scene" / "points3d.ply", pts, cols)
    _write_transforms(out / "scene", cfg, cams)
    return empty


def _render_objects(cfg, src: _Inputs, out: Path, spp_test: int, progress: bool) -> dict:
    """``objects/<name>/``: each object alone under the object map (``make_object_dataset``);
    fills each object's texture from its meta.json; returns {name: seconds}."""
    seconds = {}
    for k, (name, o) in enumerate(src.objects.items()):
        s = syn.make_object_dataset(syn.ObjectDatasetConfig(
            mesh=o["mesh"], envmap=src.object_map, out_dir=out / "objects" / name,
            n_train=cfg.object_views, n_test=cfg.test_views, resolution=cfg.resolution,
            spp=cfg.spp, spp_test=spp_test, max_depth=cfg.max_depth, relight_envmaps=(),
            envmap_scale=cfg.object_envmap_scale, seed=cfg.seed + 1 + k, fov_deg=cfg.fov_deg,
            up_axis="y", half_extent=1.0, texture=o["texture"], base_color=o["base_color"],
            roughness=o["roughness"], metallic=o["metallic"]), progress=progress)
        meta = json.loads((out / "objects" / name / "meta.json").read_text())
        assert np.allclose(meta["object"]["object_to_world"], o["object_to_world"])
        o["texture"], seconds[name] = meta["texture"], s["seconds"]
    return seconds


def _render_composites(cfg, src: _Inputs, geo: _Arrangement, textures: dict,
                       empty: "SceneRenderer", out: Path, spp_test: int, progress: bool):
    """``comp/``: spiral views of the scene with the placed objects (gt), without them (empty;
    same sampler seed) and the objects' coverage (mask). Returns (the placed objects'
    SceneSpecs, the config at the composites' resolution)."""
    specs = {name: sio.SceneSpec(
        mesh=o["mesh"], object_to_world=geo.placements[name].matrix @ o["object_to_world"],
        texture=Path(o["texture"]) if o["texture"] else None, base_color=o["base_color"],
        roughness=o["roughness"], metallic=o["metallic"], resolution=cfg.resolution,
        fov_deg=cfg.fov_deg, max_depth=cfg.max_depth, envmap_to_world=syn.ENVMAP_TO_WORLD)
        for name, o in src.objects.items()}
    comp_cams = spiral_cameras(cfg.test_views, geo.centre, geo.comp_radius,
                               azimuth0_deg=geo.az + 90.0)
    ccfg = dataclasses.replace(cfg, resolution=cfg.comp_resolution or cfg.resolution)
    full = SceneRenderer(scene_dict(ccfg, src.env, textures, geo.layout, specs))
    empty_c = empty if ccfg.resolution == cfg.resolution else \
        SceneRenderer(scene_dict(ccfg, src.env, textures, geo.layout))
    for sub in ("gt", "empty", "mask"):
        (out / "comp" / sub).mkdir(parents=True, exist_ok=True)
    for i, cam in enumerate(syn._bar(comp_cams, "composites", progress)):
        base = f"r_{i:03d}"
        for r, sub in ((full, "gt"), (empty_c, "empty")):
            rgba = r.radiance(cam["to_world_mitsuba"], spp_test, syn.render_seed(cfg.seed, i, 2))
            write_opaque(out / "comp" / sub / base, rgba, exr=True)
        write_png8(out / "comp" / "mask" / f"{base}.png", full.coverage(cam["to_world_mitsuba"]))
        cam.update(file_path=f"./gt/{base}", empty_path=f"./empty/{base}",
                   mask_path=f"./mask/{base}.png", radiance_path=f"./gt/{base}.exr",
                   empty_radiance_path=f"./empty/{base}.exr")
    _write_transforms(out / "comp", ccfg, {"test": comp_cams})
    return specs, ccfg


def _metadata(cfg, ccfg, src: _Inputs, geo: _Arrangement, specs: dict, spp_test: int,
              seconds: dict) -> dict:
    """``composition.json``: what was rendered, in which frame and colour space."""
    shapes = {k: {**sh, "to_world": sh["to_world"].tolist(), "texture": sh.get("texture") and
                  f"assets/{sh['texture']}.png"} for k, sh in geo.layout.items()}
    shapes["ground"].update(half_size=float(cfg.ground_half), top_z=0.0)
    return {
        "generator": GENERATOR_VERSION, "comgs_dr_version": package_version(),
        "mitsuba_version": mi.__version__, "variant": src.variant,
        "world": "Z-up; ground top at z = 0; scene/, comp/ and transform.json share this frame",
        "envmap_orientation": {
            "to_world_mitsuba": syn.ENVMAP_TO_WORLD.tolist(),
            "mapping": "world dir d -> u = 0.5 - atan2(d_y, d_x)/(2 pi), v = acos(d_z)/pi (v=0 "
                       "top row; Blender's Z-up equirect, as make-dataset object; all maps)"},
        "scene": {"dir": "scene", "envmap": str(src.scene_map.resolve()),
                  "envmap_scale": cfg.scene_envmap_scale, "sun_direction": geo.sun.tolist(),
                  "n_train": cfg.scene_views + cfg.sky_views, "sky_views": cfg.sky_views,
                  "sun_view": bool(cfg.sun_view),
                  "n_test": cfg.test_views,
                  "sfm_points": int(cfg.sfm_points), "camera_radius": geo.scene_radius,
                  "shapes": shapes, "bsdf": "twosided principled (specular 0.5, metallic 0); "
                  "rectangle [-1,1]^2 (normal +Z), cube [-1,1]^3, mapped by to_world"},
        "objects": _objects_metadata(cfg, src, geo, specs),
        "transforms": "transform.json maps an object's capture world (objects/<name>: the mesh "
                      "normalised by object_to_world) to the scene world; a placed mesh file's "
                      "to_world = placement @ object_to_world (= mesh_to_world)",
        "comp": {"dir": "comp", "n_test": cfg.test_views, "centre": geo.centre.tolist(),
                 "resolution": [ccfg.resolution, ccfg.resolution],
                 "camera_radius": geo.comp_radius, "cameras": "spiral: elevation 30 -> 60 deg, one "
                 "turn, looking at centre", "noise": "gt and empty of a frame share the seed"},
        "render": {"integrator": "path", "max_depth": cfg.max_depth, "fov_deg": cfg.fov_deg,
                   "resolution": [cfg.resolution, cfg.resolution], "spp_train": cfg.spp,
                   "spp_test": spp_test, "rfilter": "box", "scene_hide_emitters": False},
        "colour_space": {
            "png": "scene/ and comp/: opaque 8-bit sRGB (IEC 61966-2-1) of linear radiance "
                   "clipped to [0, 1]; objects/: see objects/<name>/meta.json (RGBA)",
            "comp_exr": "linear HDR RGBA radiance, alpha = 1",
            "mask_png": "8-bit coverage of the objects in the gt frame (16 rays per pixel)"},
        "transform_matrix": "NeRF/Blender camera-to-world (OpenGL: looks down -Z, +Y up); "
                            "to_world_mitsuba = transform_matrix @ diag(-1,1,-1,1)",
        "seconds": {k: ({n: round(x, 2) for n, x in v.items()} if isinstance(v, dict)
                        else round(v, 2)) for k, v in seconds.items()}}


def _objects_metadata(cfg, src: _Inputs, geo: _Arrangement, specs: dict) -> dict:
    """{name: files, material, capture frame, placement and world box} of each object."""
    out = {}
    for n, o in src.objects.items():
        pl = geo.placements[n]
        out[n] = {"dir": f"objects/{n}", "mesh": str(Path(o["mesh"]).resolve()),
                  "envmap": str(src.object_map.resolve()), "envmap_scale": cfg.object_envmap_scale,
                  "material": {"bsdf": "twosided principled", "texture": o["texture"],
                               "base_color": "texture" if o["texture"] else list(o["base_color"]),
                               "roughness": o["roughness"], "metallic": o["metallic"],
                               "specular": 0.5},
                  "object_to_world": o["object_to_world"].tolist(),
                  "placement": pl.matrix.tolist(),
                  "mesh_to_world": specs[n].object_to_world.tolist(),
                  "scale": pl.scale, "rotation_z_deg": float(np.degrees(np.arctan2(
                      pl.rotation[1, 0], pl.rotation[0, 0]))),
                  "bbox_world": [geo.bbox[n][0].tolist(), geo.bbox[n][1].tolist()]}
    return out


def _write_transforms(folder: Path, cfg, cams: dict) -> None:
    for split, cs in cams.items():
        frames = [{**syn._frame_json(c), **{k: c[k] for k in ("empty_path", "mask_path",
                                                              "empty_radiance_path") if k in c}}
                  for c in cs]
        (folder / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": float(np.radians(cfg.fov_deg)), "w": cfg.resolution,
             "h": cfg.resolution, "frames": frames}, indent=2))
