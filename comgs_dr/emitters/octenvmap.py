"""The ``octenvmap`` Mitsuba emitter: an octahedral environment map with exact importance
sampling, traversable and differentiable (paper, "Illumination Modeling": L_dir is an
octahedral texture).

It lights Mitsuba's own integrators (``path``, ``direct``, ``prb``…) as well as ours
(``sop_pbr``), so a scene lit by it has a path-traced reference for free.
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core import octahedral as octa
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.variant import is_kind, variant_class
from comgs_dr.lighting.envmap import EnvSampler, equirect_to_oct_np, oct_to_equirect_np, \
    read_envmap_file


class OctEnvmapBase:
    r"""
    .. _emitter-octenvmap:

    Octahedral environment map (:monosp:`octenvmap`)
    ------------------------------------------------

    .. pluginparameters::

     * - filename
       - |string|
       - An .exr/.hdr map: a 2:1 equirect map in the package's Z-up convention
         (u = 0.5 − atan2(d_y, d_x)/2π, v = acos(d_z)/π, as Blender) or an octahedral
         EXR written by this package (``layout`` metadata)
     * - data
       - |tensor|
       - Octahedral radiance [R, R, 3] (instead of ``filename``)
     * - resolution
       - |int|
       - Octahedral resolution R (Default: an equirect map's height, at most 1024; the
         file's own for octahedral files and ``data``)
     * - scale
       - |float|
       - Radiance scale, applied once at load time (Default: 1)
     * - to_world
       - |transform|
       - Rotation of the map (Default: none; the map's +Z is the world's +Z)
     * - sampling_floor
       - |float|
       - Fraction of the mean texel weight added to every texel's sampling weight, so
         that no direction has zero density (Default: 1e-3)

    Exposed parameter (``mi.traverse``): ``data``, the radiance texture [R, R, 3]
    (differentiable; the sampling table is rebuilt from it on ``update()``).

    Lookups are bilinear across the octahedron's seams (the wrap border is an index map,
    so the gradient of a border tap lands on the texel it copies). Sampling picks a texel
    ∝ luminance × solid angle (+ floor) and a uniform point inside it; the solid-angle pdf
    is exact, with the octahedral Jacobian dω/duv = 4/|q|³
    (:class:`comgs_dr.lighting.envmap.EnvSampler`).
    """

    def __init__(self, props: mi.Properties, radiance=None):
        _base(self).__init__(self, props)
        self.m_flags = mi.EmitterFlags.Infinite | mi.EmitterFlags.SpatiallyVarying
        scale = float(props.get("scale", 1.0))
        res = int(props["resolution"]) if "resolution" in props else None
        if radiance is None:
            if "data" in props:
                radiance = np.array(props["data"], np.float64)
            elif "filename" in props:
                fname = str(props["filename"])
                arr, layout = read_envmap_file(str(mi.file_resolver().resolve(fname)))
                if layout == "equirect":
                    radiance = equirect_to_oct_np(arr, res or int(np.clip(arr.shape[0], 16, 1024)))
                else:
                    radiance = arr
            else:
                raise ValueError("octenvmap: give 'filename' (an .exr/.hdr map) or 'data' "
                                 "(an [R, R, 3] tensor)")
        radiance = np.asarray(radiance, np.float64)
        if radiance.ndim != 3 or radiance.shape[0] != radiance.shape[1] or radiance.shape[2] != 3:
            raise ValueError(f"octenvmap: the octahedral map must be [R, R, 3], got {radiance.shape}")
        if res is not None and res != radiance.shape[0]:
            radiance = equirect_to_oct_np(oct_to_equirect_np(radiance, 4 * max(res, radiance.shape[0])), res)
        bad = ~np.isfinite(radiance) | (radiance < 0)
        if bad.any():
            raise ValueError(f"octenvmap: radiance must be finite and non-negative "
                             f"({int(bad.sum())} bad values)")
        if not np.isfinite(scale) or scale < 0:
            raise ValueError(f"octenvmap: 'scale' must be finite and ≥ 0, got {scale}")
        m = np.array(self.world_transform().matrix, np.float64).reshape(4, 4)[:3, :3]
        if not (np.allclose(m @ m.T, np.eye(3), atol=1e-4) and np.linalg.det(m) > 0):
            raise ValueError("octenvmap: 'to_world' must be a rotation (orthonormal, no scale, "
                             f"no mirror); got the 3×3 part {np.round(m, 4).tolist()}")
        self.floor = float(props.get("sampling_floor", 1e-3))
        self.res = radiance.shape[0]
        self.data = to_jit(mi.TensorXf, radiance * scale)
        # bordered texel -> interior texel it copies (bilinear lookups never branch)
        self._src = to_jit(mi.UInt32, octa.border_source_index(self.res))
        self.center, self.radius = mi.ScalarPoint3f(0.0), 1.0
        self._build_sampler()

    # -------------------------------------------------------------------- state
    @staticmethod
    def from_radiance(radiance, to_world=None, id: str = "envmap"):
        """An ``octenvmap`` (active variant) holding ``radiance`` [R, R, 3] (NumPy)."""
        props = mi.Properties("octenvmap")
        props.set_id(id)
        if to_world is not None:
            props["to_world"] = to_world
        return emitter_class()(props, radiance=np.asarray(radiance, np.float64))

    def _build_sampler(self):
        rad = np.array(dr.detach(self.data), np.float64).reshape(self.res, self.res, 3)
        if not np.all(np.isfinite(rad)):
            raise ValueError(f"octenvmap '{self.id()}': 'data' holds "
                             f"{int((~np.isfinite(rad)).sum())} non-finite values")
        self.sampler = EnvSampler(np.maximum(rad, 0.0), self.floor)

    def radiance_np(self) -> np.ndarray:
        """[R, R, 3] float64 radiance (detached)."""
        return np.array(dr.detach(self.data), np.float64).reshape(self.res, self.res, 3)

    def traverse(self, callback):
        callback.put("data", self.data, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=[]):
        shape = tuple(self.data.shape)
        if len(shape) != 3 or shape[0] != shape[1] or shape[2] != 3:
            raise ValueError(f"octenvmap: 'data' must stay [R, R, 3], got {shape}")
        if shape[0] != self.res:
            self.res = shape[0]
            self._src = to_jit(mi.UInt32, octa.border_source_index(self.res))
        self._build_sampler()

    def set_scene(self, scene):
        bbox = scene.bbox()
        if bbox.valid():
            bs = bbox.bounding_sphere()
            self.center = mi.ScalarPoint3f(bs.center)
            self.radius = max(float(mi.math.RayEpsilon), float(bs.radius) * (1 + float(mi.math.RayEpsilon)))
        else:
            self.center, self.radius = mi.ScalarPoint3f(0.0), float(mi.math.RayEpsilon)

    # -------------------------------------------------------------------- math
    def _to_local(self, d):
        return self.world_transform().inverse() @ mi.Vector3f(d)

    def _to_world(self, d):
        return self.world_transform() @ mi.Vector3f(d)

    def eval_world(self, d, data=None):
        """Radiance arriving from world direction ``d`` (bilinear, seamless), differentiable
        w.r.t. ``data`` (default: the emitter's texture)."""
        data = self.data if data is None else data
        flat = data.array if isinstance(data, mi.TensorXf) else data
        taps = octa.bilinear_taps(mi.UInt32(0), octa.dir_to_uv(self._to_local(d)), self.res)
        mode = octa.expand_mode(flat)
        out = mi.Color3f(0.0)
        for idx, w in zip(taps.index, taps.weight):
            texel = dr.gather(mi.UInt32, self._src, idx)
            out += w * dr.gather(mi.Color3f, flat, texel, mode=mode)
        return out

    def eval(self, si, active=True):
        return dr.select(active, self.eval_world(-si.wi), 0.0)

    def sample_world(self, u):
        """(world direction, solid-angle pdf) for ``u`` ∈ [0,1)²."""
        s = self.sampler.sample(u)
        return self._to_world(s.direction), s.pdf

    def pdf_world(self, d):
        return self.sampler.pdf(self._to_local(d))

    def sample_direction(self, it, sample, active=True):
        d, pdf = self.sample_world(sample)
        dist = 2.0 * self.radius
        ds = dr.zeros(mi.DirectionSample3f)
        ds.p = it.p + d * dist
        ds.n = -d
        ds.uv = octa.dir_to_uv(self._to_local(d))
        ds.time = it.time
        ds.pdf = pdf
        ds.delta = False
        ds.emitter = mi.EmitterPtr(self)
        ds.d = d
        ds.dist = dist
        ok = active & (pdf > 0)
        weight = dr.select(ok, self.eval_world(d) / dr.maximum(pdf, 1e-30), 0.0)
        ds.pdf = dr.select(ok, pdf, 0.0)
        return ds, mi.Color3f(weight)

    def pdf_direction(self, it, ds, active=True):
        return dr.select(active, self.pdf_world(ds.d), 0.0)

    def eval_direction(self, it, ds, active=True):
        return dr.select(active, self.eval_world(ds.d), 0.0)

    def sample_ray(self, time, wavelength_sample, sample2, sample3, active=True):
        """Light-tracing ray: a direction from the map, an origin on the disk of the scene's
        bounding sphere perpendicular to it (as Mitsuba's ``envmap``)."""
        d, pdf = self.sample_world(sample3)
        offset = mi.warp.square_to_uniform_disk_concentric(sample2)
        frame = mi.Frame3f(-d)
        perp = frame.to_world(mi.Vector3f(offset.x, offset.y, 0.0))
        origin = mi.Point3f(self.center) + (perp + d) * self.radius
        area = dr.pi * self.radius * self.radius
        ok = active & (pdf > 0)
        weight = dr.select(ok, self.eval_world(d) * area / dr.maximum(pdf, 1e-30), 0.0)
        return mi.Ray3f(origin, -d, time), mi.Color3f(weight)

    def sample_wavelengths(self, si, sample, active=True):
        return mi.Wavelength(0.0), mi.Color3f(1.0)

    def bbox(self):
        return mi.ScalarBoundingBox3f()

    def to_string(self):
        return f"OctEnvmap[id={self.id()}, resolution={self.res}]"


def is_octenvmap(obj) -> bool:
    return is_kind(obj, OctEnvmapBase)


def emitter_class():
    """The ``OctEnvmap`` class of the active variant."""
    return _make_class(mi.variant())


@functools.cache
def _make_class(variant: str):
    return variant_class("OctEnvmap", OctEnvmapBase, mi.Emitter)


def _base(obj):
    return type(obj).__bases__[0]


def register():
    mi.register_emitter("octenvmap", lambda props: emitter_class()(props))
