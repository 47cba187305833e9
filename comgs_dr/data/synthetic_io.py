"""Mitsuba scene building, rendering and image files for :mod:`comgs_dr.data.synthetic`."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np
from PIL import Image

from comgs_dr.core import exr
from comgs_dr.core.colorspace import srgb_encode
from comgs_dr.core.variant import set_variant

_MESH_TYPES = {".obj": "obj", ".ply": "ply"}


def activate_variant(name: str | None = None) -> str:
    """Keep the active JIT AD variant when ``name`` is None, else ``comgs_dr.set_variant``."""
    if name is None:
        v = mi.variant()
        if v and "_ad_" in v and not v.startswith("scalar"):
            return v
        name = "auto"
    return set_variant(name)




def load_mesh(path) -> dict:
    """Load an OBJ/PLY with Mitsuba: {'type', 'vertices' (N,3), 'has_uv', 'n_faces'}."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"mesh file not found: {p}")
    kind = _MESH_TYPES.get(p.suffix.lower())
    if kind is None:
        raise ValueError(f"mesh {p}: unsupported format '{p.suffix}' (use .obj or .ply)")
    try:
        mesh = mi.load_dict({"type": kind, "filename": str(p)})
    except Exception as e:
        raise ValueError(f"cannot load mesh {p}: {e}") from e
    v = np.array(mesh.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    if mesh.face_count() == 0 or len(v) < 3:
        raise ValueError(f"mesh {p} has no faces")
    return {"type": kind, "vertices": v, "has_uv": bool(mesh.has_vertex_texcoords()),
            "n_faces": int(mesh.face_count())}


@dataclass
class SceneSpec:
    """Everything but the lighting that defines the rendered object scene."""
    mesh: Path
    object_to_world: np.ndarray
    texture: Path | None
    base_color: tuple
    roughness: float
    metallic: float
    resolution: int
    fov_deg: float
    max_depth: int
    envmap_to_world: np.ndarray
    envmap_scale: float = 1.0


def scene_dict(spec: SceneSpec, env_bitmap) -> dict:
    """Mitsuba scene dict: the object (two-sided principled BSDF), the envmap and one sensor."""
    T = mi.ScalarTransform4f
    base = ({"type": "bitmap", "filename": str(spec.texture)} if spec.texture else
            {"type": "rgb", "value": [float(c) for c in spec.base_color]})
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(spec.max_depth), "hide_emitters": True},
        "env": {"type": "envmap", "bitmap": env_bitmap, "scale": float(spec.envmap_scale),
                "to_world": T(np.asarray(spec.envmap_to_world).tolist())},
        "object": {"type": _MESH_TYPES[spec.mesh.suffix.lower()], "filename": str(spec.mesh),
                   "to_world": T(np.asarray(spec.object_to_world).tolist()),
                   # two-sided: open meshes (the teapot's rim, thin sheets) show their back
                   "bsdf": {"type": "twosided", "material": {
                       "type": "principled", "base_color": base,
                       "roughness": float(spec.roughness),
                       "metallic": float(spec.metallic)}}},
        "sensor": {"type": "perspective", "fov": float(spec.fov_deg), "fov_axis": "x",
                   "film": {"type": "hdrfilm", "width": int(spec.resolution),
                            "height": int(spec.resolution), "pixel_format": "rgba",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
    }


class Renderer:
    """One loaded scene whose single sensor is moved per view (kernels are reused)."""

    def __init__(self, spec: SceneSpec, env_bitmap):
        self.spec = spec
        self._aov = mi.load_dict({
            "type": "aov", "aovs": "albedo:albedo,nn:sh_normal,dd:depth",
            # the inner integrator only supplies alpha (coverage) for the AOVs
            "inner": {"type": "direct", "hide_emitters": True,
                      "emitter_samples": 0, "bsdf_samples": 1}})
        self.set_envmap(env_bitmap)

    def set_envmap(self, env_bitmap) -> None:
        self.scene = mi.load_dict(scene_dict(self.spec, env_bitmap))
        self.sensor = self.scene.sensors()[0]
        self._params = mi.traverse(self.sensor)

    def _place(self, to_world: np.ndarray) -> None:
        self._params["to_world"] = mi.ScalarTransform4f(np.asarray(to_world).tolist())
        self._params.update()

    def radiance(self, to_world, spp: int, seed: int) -> np.ndarray:
        """Linear RGBA (H, W, 4): radiance premultiplied by coverage, alpha = coverage."""
        self._place(to_world)
        img = mi.render(self.scene, sensor=self.sensor, spp=int(spp), seed=int(seed))
        return np.array(img, dtype=np.float32)

    def gbuffer(self, to_world, spp: int, seed: int) -> dict:
        """Per-pixel averages over covered samples: 'albedo' (H,W,4; A = coverage),
        'normal' (H,W,4; unit world-space shading normal, A = coverage), 'depth' (H,W,1)."""
        self._place(to_world)
        mi.render(self.scene, sensor=self.sensor, integrator=self._aov, spp=int(spp),
                  seed=int(seed))
        ch = {name: np.array(b, dtype=np.float32) for name, b in
              self.sensor.film().bitmap().split()}
        cov = ch["<root>"][..., 3:4]
        inv = np.where(cov > 1e-6, 1.0 / np.maximum(cov, 1e-6), 0.0)
        n = ch["nn"].reshape(cov.shape[:2] + (3,))
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.where((norm > 1e-8) & (cov > 1e-6), n / np.maximum(norm, 1e-8), 0.0)
        return {"albedo": np.concatenate([ch["albedo"] * inv, cov], -1),
                "normal": np.concatenate([n, cov], -1),
                "depth": ch["dd"].reshape(cov.shape) * inv}


def write_png(path, rgba: np.ndarray) -> None:
    """8-bit sRGB RGBA PNG with straight alpha from premultiplied linear RGBA."""
    a = np.clip(rgba[..., 3:4], 0.0, 1.0)
    rgb = np.where(a > 1e-6, rgba[..., :3] / np.maximum(a, 1e-6), 0.0)
    out = np.concatenate([srgb_encode(np.clip(rgb, 0.0, 1.0)), a], -1)
    Image.fromarray(np.round(out * 255.0).astype(np.uint8), "RGBA").save(str(path))


def write_exr(path, arr: np.ndarray) -> None:
    """Float32 EXR (``core.exr``, atomic); 1 channel -> Y, 3 -> RGB, 4 -> RGBA."""
    exr.write_image(path, arr)
