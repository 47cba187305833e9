"""A synthetic forward-facing LLFF capture: ``poses_bounds.npy`` + ``images/`` (+ ``images_<k>/``).

The test case of step 1 on real forward-facing captures without a point cloud. A small
scene with a depth range, rendered with Mitsuba's ``path`` integrator (diffuse,
procedurally textured surfaces; a constant sky and a sun with shadows):

* a textured backdrop wall across the whole field of view at depth ~9,
* a textured floor from depth ~1.5 to the wall,
* a sphere (depth ~3.3), a rotated box (~4.9), a tilted card (~2.4) and a pillar (~6.3).

World Z-up; the cameras sit on a jittered ``rows`` x ``cols`` grid in the X–Z plane around
the origin (baseline ~0.9 x 0.5, a hand-held LLFF capture), all looking along +Y at a
common focus point at depth 6, with a small random roll/pan jitter. The folder is what
LLFF's ``imgs2poses.py`` writes, without any points::

    poses_bounds.npy   [N, 17]: [R | t | hwf] (3x5, row-major; R's columns = camera
                       [down, right, back] in world space, t = centre, hwf of images/),
                       then (near, far) = the 0.1 / 99.9 percentiles of the view's z-depths
                       (LLFF takes them from the COLMAP points' depths; here every pixel's)
    images/            image000.png ... (8-bit sRGB, ``width`` x ``height``)
    images_<k>/        the same area-downscaled by k (k in ``downscales``), as LLFF ships
    meta.json          generator settings, Mitsuba ``to_world`` per image, test split

With ``envmap`` (``make-dataset llff --envmap MAP``) a real equirect map lights the scene
instead (exposed by ``pano_data.auto_exposure`` unless ``envmap_scale``: the sky in range, a
sun clipped, as a camera would), ``backdrop=False`` removes the wall so the views see the
map's horizon, ``pitch_deg`` tilts them up to see more sky, and ``probe_height`` writes the
true light at :data:`PLACEMENT` (``probes/center.exr`` + ``probes.json``, in the
reconstruction's frame) to score ``estimate-light`` against.

``comgs reconstruct DIR --scene -r 8`` reads ``images/`` (the loader prefers it) and
area-averages 8x8 blocks, i.e. the same pixels as ``images_8/``. With the LLFF hold-out
(every 8th image by name is a test view) 20 images give 17 train + 3 test views.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from comgs_dr.core.cameras import camera_rays
from comgs_dr.core.colorspace import srgb_encode
from comgs_dr.core.hostarray import to_jit
from comgs_dr.data.images import downscale, write_png8
from comgs_dr.data.synthetic_io import activate_variant
from comgs_dr.data.placement_probe import render_probe
from comgs_dr.data.synthetic import ENVMAP_TO_WORLD
from comgs_dr.data.types import MITSUBA_FROM_LLFF, Camera, up_alignment
from comgs_dr.lighting.envmap import load_envmap, read_envmap_file, write_exr
from comgs_dr.lighting.pano_data import auto_exposure

GENERATOR_VERSION = "comgs_dr.data.llff_synthetic/2"     # 2: envmap, probe


@dataclass
class LLFFDatasetConfig:
    """Settings of :func:`make_llff_dataset` (defaults: a 4 x 5 capture whose ``images_8/``
    is what ``comgs reconstruct DIR --scene -r 8`` trains on).

    Sizes in pixels, angles in degrees, positions in world units. ``spp``: samples per
    full-resolution pixel (k² per pixel of ``images_<k>/``). ``envmap``: an equirect map that
    lights the scene instead of the constant sky and the sun (and is its sky), exposed by
    ``envmap_scale`` (None: ``pano_data.auto_exposure``: the sky in range, a sun clipped).
    ``envmap_scale``, ``envmap_rotate_deg`` and ``probe_height`` need it: the default sun is
    a directional light, which no ray can hit.

    Example: ``LLFFDatasetConfig(out_dir="ff", rows=1, cols=3, width=64, height=48,
    downscales=(2,))``.
    """
    out_dir: str | Path = "llff_synthetic"
    rows: int = 4
    cols: int = 5                         # rows x cols views (LLFF hold-out: every 8th is test)
    width: int = 800                      # images/ size; images_8/ is 100 x 75
    height: int = 600
    fov_x_deg: float = 60.0
    downscales: tuple[int, ...] = (8,)    # images_<k>/ folders written beside images/
    spp: int = 16                         # per full-resolution pixel (x k^2 after downscaling)
    max_depth: int = 4
    baseline: tuple[float, float] = (0.9, 0.5)   # grid extent in X (right) and Z (up)
    jitter: float = 0.04                  # position jitter (world units) and ...
    jitter_deg: float = 1.5               # ... rotation jitter (degrees) per view
    seed: int = 0
    variant: str | None = None            # None: keep the active JIT AD variant
    envmap: str | None = None             # an equirect map lights the scene instead of the
                                          # constant sky and the sun (and is its sky)
    envmap_scale: float | None = None     # None: pano_data.auto_exposure (sky in range)
    envmap_rotate_deg: float = 0.0        # the map turned about +Z (the views look along +Y)
    backdrop: bool = True                 # False: no wall, the views see the map's horizon
    pitch_deg: float = 0.0                # the cameras look up by this much (more sky); the
                                          # LLFF loader takes the mean camera up as +Z, so
                                          # the reconstruction's frame tilts by about as much
    probe_height: int = 0                 # > 0: probes/center.exr, the true light at PLACEMENT
                                          # (rows, at most 1024)

    def __post_init__(self):
        """Sizes, ranges and the settings that need a map, before anything is written (the
        messages name the ``make-dataset llff`` flags)."""
        for flag, v, lo in (("--rows", self.rows, 1), ("--cols", self.cols, 1),
                            ("--width", self.width, 8), ("--height", self.height, 8),
                            ("--spp", self.spp, 1)):
            if v < lo:
                raise ValueError(f"make-dataset llff: {flag} must be >= {lo}, got {v}")
        if self.rows * self.cols < 2:
            raise ValueError("make-dataset llff: need at least 2 views (--rows x --cols)")
        for flag, given in (("--envmap-scale", self.envmap_scale is not None),
                            ("--envmap-rotate", self.envmap_rotate_deg != 0.0),
                            ("--probe-height", self.probe_height > 0)):
            if given and self.envmap is None:
                raise ValueError(f"make-dataset llff: {flag} needs --envmap")
        if self.envmap_scale is not None and not 0 < self.envmap_scale < float("inf"):
            raise ValueError(f"make-dataset llff: --envmap-scale must be > 0, got {self.envmap_scale}")
        if not -60.0 <= self.pitch_deg <= 60.0:
            raise ValueError(f"make-dataset llff: --pitch must lie in [-60, 60] degrees, got "
                             f"{self.pitch_deg}")
        if not 0 <= self.probe_height <= 1024:
            raise ValueError(f"make-dataset llff: --probe-height must lie in [0, 1024], got "
                             f"{self.probe_height}")
        self._check_downscales()

    def _check_downscales(self) -> None:
        """Each ``images_<k>/`` divides the images exactly and keeps them at >= 8 px."""
        w, h, ks = self.width, self.height, self.downscales
        if any(k < 1 or w % k or h % k for k in ks):
            raise ValueError(f"make-dataset llff: each --downscale must be >= 1 and divide "
                             f"{w}x{h}, got {list(ks)}")
        small = [k for k in ks if min(w, h) // k < 8]
        if small:
            raise ValueError(f"make-dataset llff: --downscale {small[0]} makes "
                             f"{w // small[0]}x{h // small[0]} images (under 8 "
                             f"px); give a smaller --downscale (the default is 8)")


#: Where a composited object would sit: on the floor between the sphere, the box and the card
#: (world, Z-up), 0.3 above it. ``probe_height`` > 0 writes the light arriving there.
PLACEMENT = (0.2, 3.8, -1.1)


# ----------------------------------------------------------------------------- textures

def _value_noise(h: int, w: int, rng: np.random.Generator, octaves: int = 5,
                 base: int = 4) -> np.ndarray:
    """Fractal value noise [h, w] in [0, 1] (bilinear lattice noise, halving amplitude)."""
    out = np.zeros((h, w))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = base * 2 ** o
        g = rng.uniform(0, 1, (n + 1, n + 1))
        y = np.linspace(0, n, h, endpoint=False)
        x = np.linspace(0, n, w, endpoint=False)
        y0, x0 = y.astype(int), x.astype(int)
        fy, fx = (y - y0)[:, None], (x - x0)[None, :]
        fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)          # smoothstep
        a = g[y0][:, x0] * (1 - fx) + g[y0][:, x0 + 1] * fx
        b = g[y0 + 1][:, x0] * (1 - fx) + g[y0 + 1][:, x0 + 1] * fx
        out += amp * (a * (1 - fy) + b * fy)
        total += amp
        amp *= 0.5
    out /= total
    return (out - out.min()) / max(out.max() - out.min(), 1e-9)


def _palette(t: np.ndarray, colors) -> np.ndarray:
    """Map t [h, w] in [0, 1] through a piecewise-linear colour ramp -> [h, w, 3]."""
    c = np.asarray(colors, np.float64)
    x = np.linspace(0, 1, len(c))
    return np.stack([np.interp(t, x, c[:, i]) for i in range(3)], -1)


def procedural_textures(rng: np.random.Generator, size: int = 256) -> dict[str, np.ndarray]:
    """Linear-RGB albedo textures [size, size, 3] in (0, 0.9] for the scene's surfaces."""
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5) / size
    n = lambda **kw: _value_noise(size, size, rng, **kw)
    tex = {}
    # backdrop: a mottled wall with coloured blobs and a few horizontal bands
    t = n(octaves=6, base=3)
    wall = _palette(t, [(0.08, 0.12, 0.25), (0.25, 0.35, 0.55), (0.65, 0.55, 0.35), (0.85, 0.75, 0.55)])
    bands = (np.sin(2 * np.pi * 3.0 * yy + 4 * n(octaves=2, base=2)) > 0.85)[..., None]
    tex["wall"] = np.where(bands, wall * 0.4 + np.array([0.5, 0.1, 0.08]) * 0.6, wall)
    # floor: wood-like planks (stripes along the depth axis with grain noise)
    grain = n(octaves=5, base=4)
    plank = np.floor(xx * 8)
    shade = 0.75 + 0.25 * np.sin(plank * 2.3) ** 2
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (yy * 6 + 3 * grain + plank * 0.37))
    tex["floor"] = _palette(rings, [(0.25, 0.12, 0.05), (0.55, 0.32, 0.14), (0.7, 0.48, 0.25)]) \
        * shade[..., None] * (np.abs(xx * 8 - np.round(xx * 8)) > 0.03)[..., None]
    # sphere: coloured latitude stripes warped by noise
    s = 0.5 + 0.5 * np.sin(2 * np.pi * (6 * yy + 1.5 * n(octaves=3, base=3)))
    tex["sphere"] = _palette(s, [(0.7, 0.1, 0.08), (0.85, 0.8, 0.2), (0.1, 0.5, 0.2)])
    # box: a checker with noisy colours
    chk = ((np.floor(xx * 6) + np.floor(yy * 6)) % 2)[..., None]
    tex["box"] = chk * _palette(n(octaves=3), [(0.1, 0.2, 0.6), (0.2, 0.6, 0.8)]) + \
        (1 - chk) * _palette(n(octaves=3), [(0.85, 0.85, 0.8), (0.6, 0.6, 0.55)])
    # card: concentric rings + dots (fine detail close to the cameras)
    r = np.hypot(xx - 0.5, yy - 0.5)
    dots = (((xx * 10) % 1 - 0.5) ** 2 + ((yy * 10) % 1 - 0.5) ** 2 < 0.06)[..., None]
    ring = _palette(0.5 + 0.5 * np.cos(2 * np.pi * 5 * r), [(0.9, 0.45, 0.1), (0.95, 0.9, 0.8)])
    tex["card"] = np.where(dots, np.array([0.1, 0.1, 0.12]), ring)
    # pillar: vertical stripes
    tex["pillar"] = _palette(0.5 + 0.5 * np.sin(2 * np.pi * 8 * xx + 2 * n(octaves=2)),
                             [(0.3, 0.6, 0.3), (0.85, 0.85, 0.6)])
    return {k: np.clip(v, 0.02, 0.9).astype(np.float32) for k, v in tex.items()}


# ----------------------------------------------------------------------------- scene

def _diffuse(img: np.ndarray) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(img),
                                                "raw": True, "filter_type": "bilinear"}}


def scene_dict(textures: dict[str, np.ndarray], env_bitmap=None, env_scale: float = 1.0,
               backdrop: bool = True, max_depth: int = 4, env_rotate_deg: float = 0.0) -> dict:
    """Mitsuba scene dict (no sensor): the forward-facing test scene (see the module doc),
    path traced (``max_depth``, emitters visible). ``env_bitmap``: an equirect map (Z-up, the
    package's convention) times ``env_scale``, turned by ``env_rotate_deg`` about +Z, instead
    of the constant sky and the sun; ``backdrop`` False: no wall."""
    T = mi.ScalarTransform4f
    light = ({"sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.55, 0.6, 0.7]}},
              "sun": {"type": "directional", "direction": [0.45, 0.6, -0.65],
                      "irradiance": {"type": "rgb", "value": [2.6, 2.4, 2.1]}}}
             if env_bitmap is None else
             {"sky": {"type": "envmap", "bitmap": env_bitmap, "scale": float(env_scale),
                      "to_world": T().rotate([0, 0, 1], float(env_rotate_deg))
                      @ T(ENVMAP_TO_WORLD.tolist())}})
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth), "hide_emitters": False},
        **light,
        # rectangle: [-1, 1]^2 in local XY, normal +Z; rotate +90 deg about X -> normal -Y
        "wall": {"type": "rectangle", "bsdf": _diffuse(textures["wall"]),
                 "to_world": T().translate([0, 9.0, 1.0]) @ T().rotate([1, 0, 0], 90) @ T().scale([9.0, 6.0, 1.0])},
        "floor": {"type": "rectangle", "bsdf": _diffuse(textures["floor"]),
                  "to_world": T().translate([0, 5.0, -1.4]) @ T().scale([9.0, 4.0, 1.0])},
        "sphere": {"type": "sphere", "center": [-1.0, 3.3, -0.55], "radius": 0.75,
                   "bsdf": _diffuse(textures["sphere"])},
        "box": {"type": "cube", "bsdf": _diffuse(textures["box"]),
                "to_world": T().translate([1.4, 4.9, -0.75]) @ T().rotate([0, 0, 1], 35)
                @ T().scale([0.65, 0.65, 0.65])},
        "card": {"type": "rectangle", "bsdf": _diffuse(textures["card"]),
                 "to_world": T().translate([0.55, 2.4, 0.55]) @ T().rotate([0, 0, 1], -25)
                 @ T().rotate([1, 0, 0], 80) @ T().scale([0.45, 0.45, 1.0])},
        "pillar": {"type": "cylinder", "p0": [-2.4, 6.3, -1.4], "p1": [-2.4, 6.3, 2.2], "radius": 0.35,
                   "bsdf": _diffuse(textures["pillar"])},
    }
    if not backdrop:
        del d["wall"]
    return d


def grid_cameras(cfg: LLFFDatasetConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """Mitsuba ``to_world`` [4, 4] per view: jittered grid in X–Z, looking at (0, 6, 0)
    raised by ``pitch_deg``."""
    bx, bz = cfg.baseline
    xs = np.linspace(-bx / 2, bx / 2, cfg.cols) if cfg.cols > 1 else np.zeros(1)
    zs = np.linspace(bz / 2, -bz / 2, cfg.rows) if cfg.rows > 1 else np.zeros(1)
    out = []
    for z in zs:
        for x in xs:
            o = np.array([x, 0.0, z]) + rng.normal(0, cfg.jitter, 3) * [1, 0.5, 1]
            target = np.array([0.0, 6.0, 6.0 * np.tan(np.radians(cfg.pitch_deg))]) + rng.normal(0, 1, 3) * 6.0 * np.radians(cfg.jitter_deg)
            m = np.array(mi.ScalarTransform4f().look_at(origin=o.tolist(), target=target.tolist(),
                                                        up=[0, 0, 1]).matrix, float)
            roll = np.radians(rng.normal(0, cfg.jitter_deg))
            c, s = np.cos(roll), np.sin(roll)
            m[:3, :3] = m[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])  # about forward
            out.append(m)
    return out


def llff_row(to_world: np.ndarray, width: int, height: int, focal: float, near: float,
             far: float) -> np.ndarray:
    """One ``poses_bounds.npy`` row [17] from a Mitsuba ``to_world`` (inverse of the loader:
    ``[R | t] = to_world @ inv(MITSUBA_FROM_LLFF)``, then hwf, near, far)."""
    c2w = np.asarray(to_world, np.float64) @ np.linalg.inv(MITSUBA_FROM_LLFF)
    m = np.concatenate([c2w[:3, :4], np.array([[height], [width], [focal]], np.float64)], 1)
    return np.concatenate([m.ravel(), [near, far]])


def z_depths(scene, cam: Camera) -> np.ndarray:
    """Depth along the camera's forward axis [H, W] of the first hit per pixel centre
    (inf where a pixel sees nothing)."""
    d, o = camera_rays(cam.sensor_dict())
    d = np.asarray(d, np.float64).reshape(-1, 3)
    o = np.asarray(o, np.float64).reshape(-1, 3)
    si = scene.ray_intersect(mi.Ray3f(to_jit(mi.Point3f, o.T), to_jit(mi.Vector3f, d.T)))
    hit = np.asarray(si.is_valid())
    t = np.where(hit, np.asarray(si.t, np.float64), 0.0)
    z = (o + d * t[:, None] - cam.center) @ cam.to_world[:3, 2]
    return np.where(hit, z, np.inf).reshape(cam.height, cam.width)


def make_llff_dataset(cfg: LLFFDatasetConfig, progress: bool = False) -> dict:
    """Render the forward-facing capture into ``cfg.out_dir`` (see the module docstring).

    Returns the ``meta.json`` contents (settings, per-image near/far, timings).
    """
    activate_variant(cfg.variant)
    t0 = time.perf_counter()
    env, scale = _lighting(cfg)                            # checked before any folder is made
    out = Path(cfg.out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    for k in cfg.downscales:
        (out / f"images_{k}").mkdir(exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    scene = mi.load_dict(scene_dict(procedural_textures(rng), env, scale, cfg.backdrop,
                                    cfg.max_depth, cfg.envmap_rotate_deg))
    rows, names = [], []
    poses = grid_cameras(cfg, rng)
    for i, m in enumerate(poses):
        rows.append(_write_view(scene, cfg, i, m, out))
        names.append(f"image{i:03d}.png")
        if progress:
            print(f"  view {i + 1}/{len(poses)}: near {rows[-1][15]:.3f}, far {rows[-1][16]:.3f}",
                  flush=True)
    np.save(out / "poses_bounds.npy", np.asarray(rows, np.float64))
    probe = write_probe(scene, out, cfg, poses) if cfg.probe_height > 0 else None
    meta = {"envmap": None if cfg.envmap is None else str(Path(cfg.envmap).resolve()),
            "envmap_scale": scale if cfg.envmap is not None else None, "probe": probe,
            "generator": GENERATOR_VERSION,
            "config": {**asdict(cfg), "out_dir": str(cfg.out_dir)},
            "images": names, "to_world_mitsuba": [m.tolist() for m in poses],
            "near_far": [[float(r[15]), float(r[16])] for r in rows],
            "test_images": [n for i, n in enumerate(names) if i % 8 == 0],
            "seconds": time.perf_counter() - t0}
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    return meta


def _lighting(cfg: LLFFDatasetConfig):
    """(the map as an mi.Bitmap or None: the constant sky and sun, its radiance scale)."""
    if cfg.envmap is None:
        if cfg.probe_height > 0:
            raise ValueError("make_llff_dataset: probe_height needs an envmap (the default sun "
                             "is a directional light, which the probe's rays cannot hit)")
        return None, 1.0
    env = load_envmap(cfg.envmap)                         # validated (finite, 2:1, readable)
    scale = (float(cfg.envmap_scale) if cfg.envmap_scale is not None else
             auto_exposure(read_envmap_file(cfg.envmap)[0].astype(np.float64)))
    return env, scale


def _write_view(scene, cfg: LLFFDatasetConfig, i: int, to_world: np.ndarray, out: Path) -> np.ndarray:
    """Render view ``i`` into ``images/`` and each ``images_<k>/``; returns its
    ``poses_bounds.npy`` row (near/far: the 0.1 / 99.9 percentiles of its z-depths)."""
    cam = Camera(to_world, cfg.width, cfg.height, cfg.fov_x_deg)
    z = z_depths(scene, cam)
    zf = z[np.isfinite(z)]
    if zf.size == 0:
        raise RuntimeError(f"view {i} sees nothing of the scene")
    near, far = np.percentile(zf, 0.1), np.percentile(zf, 99.9)
    img = mi.render(scene, sensor=mi.load_dict(cam.sensor_dict(spp=cfg.spp)),
                    integrator=scene.integrator(), spp=cfg.spp, seed=cfg.seed * 1000 + i)
    srgb = np.clip(srgb_encode(np.clip(np.asarray(img, np.float64)[..., :3], 0, None)), 0, 1)
    name = f"image{i:03d}.png"
    write_png8(out / "images" / name, srgb)
    for k in cfg.downscales:
        write_png8(out / f"images_{k}" / name, downscale(srgb.astype(np.float32), k))
    focal = 0.5 * cfg.width / np.tan(np.radians(cfg.fov_x_deg) / 2)
    return llff_row(to_world, cfg.width, cfg.height, focal, near, far)


def write_probe(scene, out: Path, cfg: LLFFDatasetConfig, poses) -> dict:
    """``probes/center.exr``: the light arriving at :data:`PLACEMENT` (``render_probe``,
    ``cfg.probe_height`` rows, 8² strata per pixel) in the frame ``comgs reconstruct`` gives
    this folder (the LLFF loader turns the world so the mean camera up is +Z: the same
    ``up_alignment`` of the views' ``poses``), and ``probes/probes.json`` with the position in
    that frame: ``estimate-light --at`` it and ``compare-light`` against the file."""
    rot = up_alignment(list(poses), "auto", str(out))[:3, :3]                 # world -> recon
    pos = rot @ np.asarray(PLACEMENT, np.float64)
    img = render_probe(scene, PLACEMENT, int(cfg.probe_height), 8, cfg.seed,
                       world_from_probe=rot.T)
    (out / "probes").mkdir(exist_ok=True)
    path = write_exr(out / "probes" / "center.exr", img, "equirect")
    info = {"center": {"position": pos.tolist(), "position_world": list(PLACEMENT),
                       "frame": "the reconstruction's (comgs reconstruct of this folder)",
                       "height": int(cfg.probe_height), "strata_per_pixel": 64}}
    (out / "probes" / "probes.json").write_text(json.dumps(info, indent=1))
    return {"file": str(path), **info["center"]}
