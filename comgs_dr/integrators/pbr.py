"""Deferred PBR of surfel G-buffers: :class:`DeferredPbr` and the ``sop_pbr`` plugin.

Paper, "Deferred Physically Based Rendering": the G-buffers (W, D̃ = D/W, N, A, R, M) of
the surfels are rendered, covered pixels are projected to shading points x = o + D̃·d,
and each is shaded with ``lighting.shade`` (env map + occlusion/indirect light from SOPs
or from tracing). Geometry buffers are cached per sensor (step 2 keeps the step-1
geometry); material buffers are re-rendered through ``mi.render`` so gradients reach the
surfels' albedo/roughness/metallic.
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import colorspace
from ..lighting.shade import ShadingConfig, ShadingPoints, shade
from ..surfels.shape import variant_class
from .common import mitsuba_ad_base


class DeferredPbr:
    """Deferred shading of one surfel scene (surfels + sensors; any integrator).

    ``min_weight``: pixels with coverage W below this are background (not shaded).
    ``normal_offset`` is used by trace visibility (set there). Images are linear RGB,
    premultiplied by W, background added as (1 − W)·``background`` (linear).
    """

    def __init__(self, scene, env, visibility, cfg: ShadingConfig = ShadingConfig(),
                 max_hits: int = 32, min_weight: float = 0.05):
        self.scene, self.env, self.visibility, self.cfg = scene, env, visibility, cfg
        self.min_weight = float(min_weight)
        self._geo_integ = mi.load_dict({"type": "surfel_gbuffer", "max_hits": max_hits,
                                        "targets": "weight,depth_unbiased,normal"})
        self._mat_integ = mi.load_dict({"type": "surfel_gbuffer", "max_hits": max_hits,
                                        "targets": "albedo,roughness,metallic"})
        self._geo = {}

    def geometry(self, sensor: int) -> dict:
        """Cached (until :meth:`clear`) shading-point geometry of ``sensor``'s covered pixels."""
        if sensor in self._geo:
            return self._geo[sensor]
        from ..recon.losses import camera_rays
        s = self.scene.sensors()[sensor]
        with dr.suspend_grad():
            parts = self._geo_integ.split(mi.render(self.scene, sensor=s,
                                                    integrator=self._geo_integ))
            dirs, origins = camera_rays(s)
        W = np.asarray(parts["weight"])[..., 0]                            # [H, W]
        D = np.asarray(parts["depth_unbiased"])[..., 0]
        N = np.asarray(parts["normal"])
        h, w = W.shape
        nrm = np.linalg.norm(N, axis=-1)
        cover = (W >= self.min_weight) & np.isfinite(D) & (D > 0) & (nrm > 1e-6)
        pix = np.flatnonzero(cover.ravel())                                # [P]
        d = np.asarray(dirs).reshape(-1, 3)[pix]
        x = np.asarray(origins).reshape(-1, 3)[pix] + d * D.ravel()[pix, None]
        n = N.reshape(-1, 3)[pix] / nrm.ravel()[pix, None]
        f32 = lambda a: np.ascontiguousarray(a, np.float32)
        geo = {"pix": mi.UInt32(pix.astype(np.uint32)), "pix_np": pix, "shape": (h, w),
               "W": mi.Float(f32(W.ravel())), "W_np": W,
               "x": mi.Point3f(*f32(x).T), "n": mi.Vector3f(*f32(n).T),
               "wo": mi.Vector3f(*f32(-d).T)}
        self._geo[sensor] = geo
        return geo

    def clear(self):
        self._geo.clear()

    def material_buffers(self, sensor: int, params=None) -> dict:
        """Albedo/roughness/metallic tensors [H, W, c] (premultiplied by W); differentiable
        when ``params`` (``mi.traverse`` of the scene with enabled gradients) is given."""
        s = self.scene.sensors()[sensor]
        img = mi.render(self.scene, params, sensor=s, integrator=self._mat_integ)
        return self._mat_integ.split(img)

    def shading_points(self, sensor: int, params=None) -> tuple[ShadingPoints, dict]:
        geo = self.geometry(sensor)
        mats = self.material_buffers(sensor, params)
        pix, W = geo["pix"], dr.gather(mi.Float, geo["W"], geo["pix"])
        inv = dr.rcp(W)
        E = dr.ReduceMode.Expand
        a = dr.gather(mi.Color3f, mats["albedo"].array, pix, mode=E) * inv
        r = dr.gather(mi.Float, mats["roughness"].array, pix, mode=E) * inv
        m = dr.gather(mi.Float, mats["metallic"].array, pix, mode=E) * inv
        pts = ShadingPoints(position=geo["x"], normal=geo["n"], wo=geo["wo"],
                            albedo=dr.clip(a, 0.0, 1.0), roughness=dr.clip(r, 0.0, 1.0),
                            metallic=dr.clip(m, 0.0, 1.0))
        return pts, geo

    def render(self, sensor: int, params=None, seed: int = 0, background=0.0,
               display: bool = False, env_theta=None):
        """Image [H, W, 3] (``mi.TensorXf``): linear (default) or display sRGB, background
        blended by coverage. Differentiable w.r.t. materials/env/probe atlas."""
        pts, geo = self.shading_points(sensor, params)
        c = shade(pts, self.env, self.visibility, self.cfg, seed, env_theta)      # [P]
        return self.compose(c, geo, background, display)

    @staticmethod
    def compose(c, geo, background=0.0, display=False):
        h, w = geo["shape"]
        Wp = dr.gather(mi.Float, geo["W"], geo["pix"])
        bg = mi.Color3f(background)
        if display:
            c = colorspace.linear_to_srgb(c)
        img = dr.zeros(mi.Color3f, h * w)
        # premultiplied by coverage, background behind (in the output's space)
        dr.scatter(img, Wp * c, geo["pix"])
        Wall = geo["W"]
        keep = dr.zeros(mi.Float, h * w)
        dr.scatter(keep, 1.0, geo["pix"])
        img = img + (1.0 - Wall * keep) * bg
        flat = dr.ravel(img)         # [H*W*3] interleaved
        return mi.TensorXf(flat, shape=(h, w, 3))


# ---------------------------------------------------------------------------------------
# The ``sop_pbr`` Mitsuba plugin (primal rendering)

class SopPbrBase:
    r"""
    .. _integrator-sop_pbr:

    SOP deferred PBR (:monosp:`sop_pbr`)
    ------------------------------------

    .. pluginparameters::

     * - envmap
       - |string|
       - Environment map file (.exr/.hdr, equirect or our octahedral EXR) (required)
     * - envmap_scale
       - |float|
       - Radiance scale of the map (Default: 1)
     * - envmap_res
       - |int|
       - Octahedral resolution the map is resampled to (Default: 256)
     * - visibility
       - |string|
       - ``sops`` (needs ``probes``), ``trace`` or ``none`` (Default: sops if ``probes``
         is given, else trace)
     * - probes
       - |string|
       - Probe file written by ``comgs decompose`` / ``sops.ProbeSet.save``
     * - rays
       - |int|
       - S_r, directions per shading point (Default: 256, the paper's rendering count)
     * - indirect
       - |bool|
       - Add indirect light L_in (Default: true)
     * - max_hits / trace_hits
       - |int|
       - Surfels composited per camera ray / per visibility ray (Default: 32 / 8)
     * - trace_offset
       - |float|
       - Visibility ray origin offset along the normal, scene units (Default: 1e-3 of the
         scene's bounding-box diagonal)

    Renders linear RGB (coverage-premultiplied over a black background). Every shape must
    be a ``surfels`` shape carrying materials. Only the primal is implemented: optimise
    with ``comgs_dr.recon.train_material`` (which differentiates :class:`DeferredPbr`).
    """

    def __init__(self, props: mi.Properties):
        type(self).__bases__[0].__init__(self, props)
        from ..lighting.envmap import OctEnvmap
        if "envmap" not in props:
            raise ValueError("sop_pbr: the 'envmap' parameter (a file name) is required")
        self.env = OctEnvmap.from_file(str(props["envmap"]), int(props.get("envmap_res", 256)),
                                       float(props.get("envmap_scale", 1.0)))
        self.probes_path = str(props["probes"]) if "probes" in props else None
        self.visibility_kind = str(props.get("visibility", "sops" if self.probes_path else "trace"))
        if self.visibility_kind not in ("sops", "trace", "none"):
            raise ValueError(f"sop_pbr: 'visibility' must be sops, trace or none, got "
                             f"{self.visibility_kind!r}")
        if self.visibility_kind == "sops" and not self.probes_path:
            raise ValueError("sop_pbr: visibility 'sops' needs the 'probes' file parameter")
        self.cfg = ShadingConfig(rays=int(props.get("rays", 256)),
                                 indirect=bool(props.get("indirect", True)))
        self.max_hits = int(props.get("max_hits", 32))
        self.trace_hits = int(props.get("trace_hits", 8))
        self.trace_offset = float(props.get("trace_offset", -1.0))
        self._probes = None

    def _visibility(self, scene):
        from ..lighting.shade import NoVisibility, SopVisibility, TraceVisibility
        if self.visibility_kind == "none":
            return NoVisibility()
        if self.visibility_kind == "trace":
            off = self.trace_offset if self.trace_offset > 0 else 1e-3 * float(
                dr.norm(scene.bbox().extents()))
            return TraceVisibility(scene, off, self.trace_hits)
        if self._probes is None:
            from ..sops.probes import ProbeSet
            from ..sops.query import ProbeGrid
            p = ProbeSet.load(self.probes_path)
            self._probes = (p, ProbeGrid(p.positions, p.radius))
        p, grid = self._probes
        return SopVisibility(p.atlas(), grid, p.res)

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not develop:
            raise RuntimeError("sop_pbr: only develop=True rendering is supported")
        idx = sensor if isinstance(sensor, int) else list(scene.sensors()).index(sensor)
        with dr.suspend_grad():
            pbr = DeferredPbr(scene, self.env, self._visibility(scene), self.cfg, self.max_hits)
            img = pbr.render(idx, seed=seed)
            dr.eval(img)
        return img

    def render_forward(self, *args, **kwargs):
        raise NotImplementedError("sop_pbr: derivatives go through "
                                  "comgs_dr.integrators.pbr.DeferredPbr (see train_material)")

    render_backward = render_forward

    def to_string(self):
        return f"SopPbrIntegrator[visibility={self.visibility_kind}, rays={self.cfg.rays}]"


def integrator_class():
    return _make_class(mi.variant())


@functools.cache
def _make_class(variant: str):
    return variant_class("SopPbrIntegrator", SopPbrBase, mitsuba_ad_base("ADIntegrator"))


def register():
    mi.register_integrator("sop_pbr", lambda props: integrator_class()(props))
