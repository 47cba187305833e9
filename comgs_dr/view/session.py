"""The work of ``comgs view`` without a browser: :class:`ViewSession`.

A session holds one composition folder (``comgs compose``'s ``COMP_DIR``) and the placement
of each object in the reconstruction's world frame. :meth:`ViewSession.move` puts one object
at a new object→world matrix and re-runs the edit stage (``stages.compose.compose``, the
stage's own public function) on the folder: the moved object is lit at its new centre (its
estimate, or the composition's one map when it was composed with ``--env``), every other
object keeps its map byte for byte, and compose's cache (keys of files, placements and
settings) re-traces only the occlusion pairs the moved object is part of.
:meth:`ViewSession.render` renders the composite (``stages.render_comp.load_comp_scene``)
from any camera dict (``data.comp_folder.camera``); :meth:`ViewSession.save` writes the
placements to ``transform.json`` (the scene dataset's frame, as ``compose --placement``
reads it). :func:`viewer_camera` turns a viser camera (OpenCV axes, vertical field of view)
into such a camera dict.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.colorspace import srgb_encode
from comgs_dr.core.similarity import Similarity, from_matrix
from comgs_dr.data import comp_folder
from comgs_dr.data.exposure import ExposureGain
from comgs_dr.lighting import envmap as em
from comgs_dr.sops.occlusion import ShadowConfig
from comgs_dr.stages.compose import ComposeConfig, compose
from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light, write_outputs
from comgs_dr.stages.render_comp import VARIANTS, load_comp_scene
from comgs_dr.surfels.io import load_ply
from comgs_dr.surfels.params import SurfelParams
from comgs_dr.surfels.transform import quat_from_matrix
from comgs_dr.surfels.shape import SurfelShapeBase
from comgs_dr.surfels.transform import transform_surfels
from comgs_dr.train.checkpoint import atomic_write_text

log = logging.getLogger(__name__)

LIGHT_MODES = ("estimate", "keep")
CV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0])      # OpenCV camera axes (x right, y down) → Mitsuba's


@dataclass
class ViewConfig:
    """Settings of ``comgs view``.

    host, port: where the viser server listens (port 0: a free one, printed).
    res: size (px a side) of the composite shown after each move, rendered from the
        viewer's camera with its vertical field of view (default 128).
    full_res: size of "render full size", px a side (None: the scene capture's width, at
        least ``res``).
    variant: composite shown first: sop, trace, noshadow or paste (a dropdown switches it).
    rays: the integrator's rays per pixel of the preview (default 16; None: its 256).
    full_rays: rays per pixel of "render full size" (None: the integrator's 256).
    light: "estimate" (default): a moved object is lit by the estimate at its new centre
        (when the composition's lighting was estimated; a composition made with ``--env``
        keeps its one map); "keep": it keeps its current map (a faster move).
    label: scene label of that estimation (None: auto, classified from the panorama).
    pano: width of the panorama that estimation traces and completes (height half; default
        128: ~1 s on 2 cores, where ``compose``'s 1024 takes ~30 s; on the tiny demo the
        irradiance and mean radiance of the 128 and 1024 estimates agree to 3 digits).
    sun_from_shadows: "off" (default) or "auto": also fit a sun to the scene's cast shadows
        at each move, as ``compose`` does (``EstimateConfig.sun_from_shadows``; 10-25 s a
        move on 2 cores).
    points: scene surfels shown as points in the viewer (at most; default 30000).
    placement: the transform.json "save placement" writes (None: COMP_DIR/transform.json);
        entries of other objects already in it are kept.
    """
    host: str = "127.0.0.1"
    port: int = 8080
    res: int = 128
    full_res: int | None = None
    variant: str = "sop"
    rays: int | None = 16
    full_rays: int | None = None
    light: str = "estimate"
    label: str | None = None
    pano: int = 128
    sun_from_shadows: str = "off"
    points: int = 30000
    placement: str | None = None

    def validate(self) -> None:
        """ValueError naming the first setting the viewer cannot use."""
        if self.variant not in VARIANTS:
            raise ValueError(f"view: variant must be one of {', '.join(VARIANTS)}, got "
                             f"{self.variant!r}")
        if self.light not in LIGHT_MODES:
            raise ValueError(f"view: light must be one of {', '.join(LIGHT_MODES)}, got "
                             f"{self.light!r}")
        if self.sun_from_shadows not in ("auto", "off"):
            raise ValueError(f"view: sun_from_shadows must be auto or off, got "
                             f"{self.sun_from_shadows!r}")
        for k, top in (("res", 16384), ("full_res", 16384), ("rays", 1 << 16),
                       ("full_rays", 1 << 16), ("points", 1 << 24), ("pano", 8192)):
            v = getattr(self, k)
            if v is not None and (isinstance(v, bool) or int(v) != v or not 1 <= v <= top):
                raise ValueError(f"view: {k} must be an integer in [1, {top}], got {v!r}")
        if self.pano % 2:
            raise ValueError(f"view: pano must be even (a 2:1 panorama), got {self.pano}")
        if not 0 <= int(self.port) <= 65535:
            raise ValueError(f"view: port must be in [0, 65535], got {self.port!r}")


def _compose_config(d: dict) -> ComposeConfig:
    """The manifest's ``config`` record back as the :class:`ComposeConfig` it was made with."""
    d = dict(d or {})
    shadow = ShadowConfig(**d.pop("shadow", {}))
    names = {f.name for f in dataclasses.fields(ComposeConfig)}
    return ComposeConfig(shadow=shadow, **{k: v for k, v in d.items() if k in names})


def _exposure(rec: dict | None) -> ExposureGain | None:
    """The manifest's exposure record of an object back as its :class:`ExposureGain`."""
    if not rec:
        return None
    return ExposureGain(gain=tuple(rec["gain"]), method=rec["method"],
                        assumed=rec.get("assumed", ""), detail=rec.get("detail", {}))


def viewer_camera(position, wxyz, fov_y: float, width: int, height: int,
                  name: str = "view") -> dict:
    """A ``comp_folder.camera`` dict of a viser camera: ``position`` [3], ``wxyz`` the
    camera-to-world rotation (OpenCV axes: +Z forward, +Y down), ``fov_y`` the vertical
    field of view (radians); square pixels, the principal point in the centre."""
    w, x, y, z = (float(v) for v in wxyz)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    r_cv = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r_cv @ CV_TO_MITSUBA
    m[:3, 3] = np.asarray(position, np.float64)
    f = 0.5 * int(height) / np.tan(0.5 * float(fov_y))
    return comp_folder.camera(name, m, int(width), int(height), f, f, 0.5 * int(width),
                              0.5 * int(height))


def camera_pose_cv(cam: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """(position [3], wxyz (OpenCV axes), vertical field of view in radians) of a
    ``comp_folder.camera`` dict: what a viser camera is set to."""
    m = np.asarray(cam["to_world"], np.float64)
    r = m[:3, :3] @ CV_TO_MITSUBA
    r = r / np.cbrt(np.linalg.det(r))
    return m[:3, 3].copy(), rotation_wxyz(r), float(2 * np.arctan(0.5 * cam["height"] / cam["fy"]))


#: The unit quaternion (w, x, y, z) of a rotation matrix: viser's convention is the surfels'.
rotation_wxyz = quat_from_matrix


def wxyz_rotation(q) -> np.ndarray:
    """The rotation matrix of a quaternion (w, x, y, z) (normalised first)."""
    return viewer_camera(np.zeros(3), q, 1.0, 2, 2)["to_world"][:3, :3] @ CV_TO_MITSUBA


class ViewSession:
    """One composition folder being edited (see the module docstring).

    ``say``: where progress lines go.
    """

    def __init__(self, comp_dir, cfg: ViewConfig | None = None, say: Callable = log.info):
        self.cfg = cfg or ViewConfig()
        self.cfg.validate()
        self.comp = Path(comp_dir)
        self.say = say
        self.manifest = comp_folder.read_manifest(self.comp)
        m = self.manifest
        if not m["objects"]:
            raise ValueError(f"{self.comp}: the composition has no object to move")
        self.W = np.asarray(m.get("world_from_source", np.eye(4)), np.float64)
        self.names = list(m["objects"])
        self.runs = {n: o["run"] for n, o in m["objects"].items()}
        self.world = {n: from_matrix(o["placement"], n) for n, o in m["objects"].items()}
        self.compose_cfg = _compose_config(m.get("config"))
        self.exposure = {n: _exposure(o.get("exposure")) for n, o in m["objects"].items()}
        self.env = m.get("lighting", {}).get("file")        # composed with one map (--env)
        if self.env is not None and not Path(self.env).is_file():
            raise FileNotFoundError(f"{self.comp}: the composition's map {self.env} is missing")
        self._backend = None
        self._scenes: dict = {}
        self._loaded_once = False     # the first scene: load_comp_scene's, checking files
        self._plys: dict = {}         # {(PLY path, size, mtime): its surfels (to_numpy)}
        self.moves = 0
        self.last_edit: dict | None = None

    # ------------------------------------------------------------------ placements

    @property
    def placement_path(self) -> Path:
        return Path(self.cfg.placement) if self.cfg.placement else self.comp / "transform.json"

    def source_placements(self) -> dict:
        """{name: Similarity} in the scene dataset's frame (transform.json's)."""
        w_inv = np.linalg.inv(self.W)
        return {n: from_matrix(w_inv @ s.matrix, n) for n, s in self.world.items()}

    def save(self, path=None) -> Path:
        """Write every object's placement to ``path`` (None: :attr:`placement_path`) as
        row-major ``transform`` entries in the scene dataset's frame; entries of other
        objects already in the file are kept."""
        p = Path(path) if path is not None else self.placement_path
        data = {}
        if p.is_file():
            try:
                data = json.loads(p.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError):
                data = {}
            data = data if isinstance(data, dict) else {}
        for n, s in self.source_placements().items():
            data[n] = {"transform": s.matrix.ravel().tolist()}
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(p, json.dumps(data, indent=1))
        return p

    def bounds(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.manifest["objects"][name]["bounds"]
        return np.asarray(lo, np.float64), np.asarray(hi, np.float64)

    # ------------------------------------------------------------------ the edit

    def move(self, name: str, matrix) -> dict:
        """Place object ``name`` at the object→world ``matrix`` (4×4, the reconstruction's
        frame; a similarity) and re-run the edit stage for it. Returns {"name", "seconds",
        "lighting" (seconds), "traced", "reused", "culled" (occlusion pairs), "recomputed"}."""
        if name not in self.world:
            raise ValueError(f"view: no object {name!r} (objects: {', '.join(self.names)})")
        t = time.perf_counter()
        new = from_matrix(np.asarray(matrix, np.float64), name)
        old = self.world[name]
        self.world[name] = new
        try:
            summary = self._recompose(name)
        except BaseException:
            self.world[name] = old
            raise
        self.manifest = comp_folder.read_manifest(self.comp)
        self._scenes.clear()
        self.moves += 1
        p = summary["pairs"]
        self.last_edit = {"name": name, "seconds": time.perf_counter() - t,
                          "lighting": summary["timings"].get("lighting", 0.0),
                          "traced": p["traced"], "reused": p["reused"], "culled": p["culled"],
                          "recomputed": summary["recomputed"]}
        return self.last_edit

    def _recompose(self, moved: str) -> dict:
        """``compose`` on the folder with the current placements; every object but ``moved``
        (and ``moved`` too with ``light="keep"``) keeps its map file as it was."""
        keep = [n for n in self.names if n != moved or self.cfg.light == "keep"]
        kept = {n: (self.comp / self.manifest["objects"][n]["envmap"]).read_bytes()
                for n in keep}
        estimator = None
        if self.env is None:
            estimator = self._lighting_of(moved if self.cfg.light == "estimate" else None)
        try:
            return compose(self.manifest["scene"]["run"], self.runs, self.source_placements(),
                           self.comp, env=self.env, estimator=estimator, cfg=self.compose_cfg,
                           progress=False, exposure=self.exposure)
        finally:
            for n, data in kept.items():           # the kept maps, byte for byte
                (self.comp / self.manifest["objects"][n]["envmap"]).write_bytes(data)

    def _lighting_of(self, moved: str | None):
        """compose's ``estimator``: the estimate at the placement for ``moved``; for every
        other object its current map as equirect (a stand-in: the file is restored)."""
        def estimator(pos, name):
            if name == moved:
                return self.estimate(pos, name)
            img, layout = em.read_envmap_file(self.comp / self.manifest["objects"][name]["envmap"])
            return img if layout != "octahedral" else em.oct_to_equirect_np(img, 2 * img.shape[0])
        return estimator

    def estimate(self, pos, name: str) -> np.ndarray:
        """The light at ``pos`` (``stages.estimate_light.estimate_light`` on the scene run's
        PLY, a ``cfg.pano``-wide panorama): equirect radiance [H, W, 3]; its files written
        to ``env/<name>_estimate/`` as ``compose`` keeps them."""
        from comgs_dr.lighting import backends
        if self._backend is None:
            self._backend = backends.default_backend()
        cfg = EstimateConfig(width=self.cfg.pano, height=self.cfg.pano // 2,
                             oct_res=min(self.compose_cfg.env_res, self.cfg.pano // 2),
                             label=self.cfg.label or "auto",
                             sun_from_shadows=self.cfg.sun_from_shadows)
        ply = Path(self.manifest["scene"]["run"]) / "point_cloud.ply"
        import torch
        threads = torch.get_num_threads()
        torch.set_num_threads(1)       # the small completion net: 0.2 s, not 3-12 s on a
        try:                           # busy 2-core machine where idle workers spin
            r = estimate_light(str(ply), np.asarray(pos, np.float64), cfg, self._backend)
        finally:
            torch.set_num_threads(threads)
        write_outputs(r, self.comp / "env" / f"{name}_estimate" / f"{name}.exr")
        self.say(f"lighting of {name!r} estimated at {np.round(pos, 3).tolist()} in "
                 f"{r['timings']['total']:.2f} s")
        return r["hdr"]

    # ------------------------------------------------------------------ rendering

    def scene(self, variant: str | None = None, rays: int | None = None):
        """The composition's Mitsuba scene for ``variant`` (kept until the next move)."""
        variant = variant or self.cfg.variant
        key = (variant, rays)
        if key not in self._scenes:
            extra = {"rays": int(rays), "shadow_rays": int(rays)} if rays else {}
            self._scenes[key] = self._load_scene(variant, extra)
        return self._scenes[key]

    def _load_scene(self, variant: str, extra: dict):
        """``stages.render_comp.load_comp_scene``'s scene, its surfels shapes built from
        the PLYs this session has read (each read once: a 20k-surfel PLY takes ~0.7 s to
        read, placing it 0.02 s); the first one is ``load_comp_scene``'s own, which checks
        the folder's files (the PLYs are read then too, not on the first move)."""
        m = self.manifest
        if not self._loaded_once:
            scene = load_comp_scene(self.comp, variant, **extra)
            self._loaded_once = True
            for d in comp_folder.shape_dicts(m).values():
                self._surfels(d["filename"])
            return scene
        shapes = {}
        for k, d in comp_folder.shape_dicts(m).items():
            params = SurfelParams.from_numpy(**self._surfels(d["filename"]))
            if k != "scene":
                params = transform_surfels(params, from_matrix(m["objects"][k]["placement"], k))
            shapes[k] = SurfelShapeBase.from_params(params, id=k)
        props = comp_folder.integrator_props(self.comp, m, variant, **extra)
        return mi.load_dict({"type": "scene", "integrator": props, **shapes})

    def _surfels(self, path) -> dict:
        """The surfels of PLY ``path`` (``to_numpy``), read once per file version."""
        p = Path(path).resolve()
        st = p.stat()
        key = (str(p), st.st_size, st.st_mtime_ns)
        if key not in self._plys:
            self._plys[key] = load_ply(str(p)).to_numpy()
        return self._plys[key]

    def render(self, cam: dict, variant: str | None = None, rays: int | None = -1,
               seed: int = 0) -> np.ndarray:
        """The composite from camera dict ``cam`` as a display image (sRGB in [0, 1],
        [H, W, 3] float32); ``rays``: -1 the preview's (``cfg.rays``), None the
        integrator's default."""
        rays = self.cfg.rays if rays == -1 else rays
        scene = self.scene(variant, rays)
        clip = comp_folder.clip_for(self.manifest, [cam])
        sensor = mi.load_dict(comp_folder.sensor_dict(cam, clip=clip))
        img = mi.render(scene, sensor=sensor, seed=seed)
        dr.eval(img)
        lin = np.asarray(img, np.float32)[..., :3]
        if not np.all(np.isfinite(lin)):
            raise FloatingPointError("view: the composite has non-finite pixels")
        return np.clip(srgb_encode(np.clip(lin, 0.0, None)), 0.0, 1.0).astype(np.float32)

    def capture_cameras(self) -> list[dict]:
        """The scene capture's cameras (test views, else training views) as camera dicts."""
        from comgs_dr.train.run import load_run_dataset, read_run_info
        run = Path(self.manifest["scene"]["run"])
        data = load_run_dataset(run, read_run_info(run), pixels=False)
        return [comp_folder.camera(v.name, c.to_world, c.width, c.height, c.fx,
                                   c.fx * c.fy_over_fx, c.cx, c.cy)
                for v in (data.train or data.test) for c in (v.camera,)]

    def home_camera(self, width: int | None = None) -> dict:
        """The capture camera closest to looking at the objects' centre, at ``width`` px
        wide (None: its own size)."""
        cams = self.capture_cameras()
        c = np.mean([np.add(*self.bounds(n)) / 2 for n in self.names], 0)

        def score(cam):
            m = np.asarray(cam["to_world"])
            d = c - m[:3, 3]
            return -float(np.dot(d / np.linalg.norm(d), m[:3, 2]))
        cam = min(cams, key=score)
        if width is None:
            return cam
        return comp_folder.sized(cam, width, max(1, round(width * cam["height"] / cam["width"])))

    # ------------------------------------------------------------------ what the viewer shows

    def scene_points(self, limit: int | None = None, seed: int = 0):
        """(positions [N, 3], colours [N, 3] uint8) of the scene's opaque surfels (at most
        ``limit``, a random subset): their step-1 radiance (SH band 0)."""
        return _points(self.manifest["scene"]["ply"], limit or self.cfg.points, seed, "sh")

    def object_points(self, name: str, limit: int = 5000, seed: int = 0):
        """(positions [N, 3] in the object's own frame, colours [N, 3] uint8: albedo)."""
        return _points(self.manifest["objects"][name]["ply"], limit, seed, "albedo")


def _points(ply, limit: int, seed: int, colour: str):
    from comgs_dr.surfels.params import base_colour
    d = load_ply(str(ply)).to_numpy()
    op = 1.0 / (1.0 + np.exp(-np.asarray(d["opacity_logit"], np.float64)))
    keep = np.flatnonzero(op > 0.3)
    if len(keep) == 0:
        keep = np.arange(len(op))
    if len(keep) > limit:
        keep = np.sort(np.random.default_rng(seed).choice(keep, limit, replace=False))
    pos = np.asarray(d["means"], np.float32)[keep]
    if colour == "sh" and d.get("sh") is not None:
        rgb = base_colour(np.asarray(d["sh"], np.float32)[keep])
    else:
        rgb = srgb_encode(np.clip(np.asarray(d["albedo"], np.float32)[keep], 0, 1))
    return pos, (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
