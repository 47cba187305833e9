"""Deferred PBR of surfel G-buffers: :class:`DeferredPbr` and the ``sop_pbr`` plugin.

Paper, "Deferred Physically Based Rendering": the G-buffers (W, D̃ = D/W, N, A, R, M) of
the surfels are rendered, covered pixels are projected to shading points x = o + D̃·d,
and each is shaded with ``lighting.shade`` (env map + occlusion/indirect light from SOPs
or from tracing).

Geometry is fixed while materials are optimised (step 2 keeps the step-1 geometry), so per
sensor the geometry buffers *and* each covered pixel's composite weights w_ik = T_k α_k
over its hit surfels are computed once and cached. A material buffer is then the exact
alpha-blend B(p) = Σ_k w_pk b_{i_k} (paper eq. Multi-Target Rendering), evaluated as a
gather over the cached hits — differentiable w.r.t. the per-surfel materials, with no
re-trace and no custom backward pass (measured much cheaper than ``mi.render`` of the
material targets on every iteration).
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
        self._mat_integ = mi.load_dict({"type": "surfel_gbuffer", "max_hits": max_hits,
                                        "targets": "albedo,roughness,metallic"})
        self._geo = {}
        self.max_hits = max_hits

    def geometry(self, sensor: int) -> dict:
        """Cached (until :meth:`clear`) shading-point geometry of ``sensor``'s covered pixels."""
        if sensor in self._geo:
            return self._geo[sensor]
        from ..recon.losses import camera_rays
        s = self.scene.sensors()[sensor]
        from . import common
        from .compositing import trace_composite
        shapes = common.surfel_shapes(self.scene, "DeferredPbr")
        if len(shapes) != 1:
            raise ValueError(f"DeferredPbr: needs exactly one surfels shape, got {len(shapes)}")
        K = self.max_hits
        with dr.suspend_grad():
            dirs, origins = camera_rays(s)
            h, w = dirs.shape[:2]
            ray = mi.Ray3f(mi.Point3f(dr.unravel(mi.Point3f, origins.array)),
                           mi.Vector3f(dr.unravel(mi.Vector3f, dirs.array)))
            eps = common.auto_epsilon(self.scene, shapes)
            hits, out, _, _ = trace_composite(self.scene, shapes, ray, K, eps,
                                              ("weight", "depth_unbiased", "normal"))
            W, D, N = out["weight"], out["depth_unbiased"], out["normal"]
            nrm = dr.norm(N)
            cover = (W >= self.min_weight) & dr.isfinite(D) & (D > 0) & (nrm > 1e-6)
            pix = dr.compress(cover)                                           # [P]
            d = dr.gather(mi.Vector3f, ray.d, pix)
            o = dr.gather(mi.Point3f, ray.o, pix)
            x = mi.Point3f(o + d * dr.gather(mi.Float, D, pix))
            n = mi.Vector3f(dr.gather(mi.Vector3f, N, pix) / dr.gather(mi.Float, nrm, pix))
            # blend weights T_k α_k of every covered pixel's hits (recomputed analytically)
            P = dr.width(pix)
            rid = dr.arange(mi.UInt32, P)
            ids = dr.zeros(mi.UInt32, P * K)
            wts = dr.zeros(mi.Float, P * K)
            count = dr.gather(mi.UInt32, hits.count, pix)
            pray = mi.Ray3f(o, d)

            def body(k, T):     # symbolic loop: compile time independent of K
                idx = dr.gather(mi.UInt32, hits.ids, pix * K + k)
                smp = common.eval_surfel(shapes, mi.UInt32(0), idx, pray, True)
                dr.scatter(ids, idx, rid * K + k)
                dr.scatter(wts, T * smp.alpha, rid * K + k)
                return k + 1, T * (1.0 - smp.alpha)

            dr.while_loop((mi.UInt32(0), dr.full(mi.Float, 1.0, P)),
                          lambda k, T: k < count, body, label="blend weights")
            dr.eval(ids, wts, x, n, d, W)
        geo = {"pix": pix, "pix_np": np.asarray(pix, np.int64), "shape": (h, w),
               "W": W, "W_np": np.asarray(W).reshape(h, w), "x": x, "n": n, "wo": mi.Vector3f(-d),
               "ids": ids, "w": wts}
        self._geo[sensor] = geo
        return geo

    def surfel_materials(self) -> dict:
        """The scene's per-surfel materials (albedo Color3f, roughness, metallic)."""
        p = self.scene.shapes()[0].params
        return {"albedo": p.albedo, "roughness": p.roughness, "metallic": p.metallic}

    def clear(self):
        self._geo.clear()

    def material_buffers(self, sensor: int, params=None) -> dict:
        """Albedo/roughness/metallic tensors [H, W, c] (premultiplied by W) rendered with
        ``mi.render`` (reference path; differentiable when ``params`` is given)."""
        s = self.scene.sensors()[sensor]
        img = mi.render(self.scene, params, sensor=s, integrator=self._mat_integ)
        return self._mat_integ.split(img)

    def shading_points(self, sensor: int, materials: dict | None = None
                       ) -> tuple[ShadingPoints, dict]:
        """Shading points of ``sensor``'s covered pixels. ``materials``: per-surfel
        {'albedo', 'roughness', 'metallic'} (default: the scene's), e.g. the optimiser's
        variables — gradients flow to them through the blend."""
        geo = self.geometry(sensor)
        mats = materials if materials is not None else self.surfel_materials()
        K = self.max_hits
        from ..sops.octahedral import expand_mode
        ids, w = geo["ids"], geo["w"]
        W = dr.block_sum(w, K)                                              # [P]
        inv = dr.rcp(dr.maximum(W, 1e-6))

        def blend(cls, src):
            return dr.block_sum(w * dr.gather(cls, src, ids, mode=expand_mode(src)), K) * inv
        a = blend(mi.Color3f, mats["albedo"])
        r = blend(mi.Float, mats["roughness"])
        m = blend(mi.Float, mats["metallic"])
        pts = ShadingPoints(position=geo["x"], normal=geo["n"], wo=geo["wo"],
                            albedo=dr.clip(a, 0.0, 1.0), roughness=dr.clip(r, 0.0, 1.0),
                            metallic=dr.clip(m, 0.0, 1.0))
        return pts, geo

    def render(self, sensor: int, materials: dict | None = None, seed: int = 0,
               background=0.0, display: bool = False, env_theta=None):
        """Image [H, W, 3] (``mi.TensorXf``): linear (default) or display sRGB, background
        blended by coverage. Differentiable w.r.t. materials/env/probe atlas."""
        pts, geo = self.shading_points(sensor, materials)
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
