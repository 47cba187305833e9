"""The ``sop_pbr`` Mitsuba integrator: differentiable deferred PBR of relightable surfels
(paper, "Deferred Physically Based Rendering" and "Illumination Modeling").

Camera rays find the surfels' hits once per sensor (cached: geometry is fixed in step 2,
and the cache is dropped when the surfels' geometry parameters change); each covered pixel
becomes a shading point whose materials are the exact alpha-blend of its hits' albedo,
roughness and metallic, shaded under the scene's ``octenvmap`` emitter with occlusion and
indirect light from Surface Octahedral Probes (or traced, or none)
(:func:`comgs_dr.shading.shade.shade`). ``mi.render(scene, params)`` + ``dr.backward``
give gradients for the surfels' materials (``<shape>.albedo|roughness|metallic``), the
emitter's texture (``<emitter>.data``) and the probe textures (``probe_data`` of this
integrator: ``mi.traverse(integrator)``).
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi

from comgs_dr.core import octahedral as octa
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.variant import AttachedRender, mitsuba_ad_base, variant_class
from comgs_dr.emitters.octenvmap import emitter_class, is_octenvmap
from comgs_dr.shading.deferred import DeferredPbr
from comgs_dr.shading.shade import SAMPLINGS, ShadingConfig, shade
from comgs_dr.shading.visibility import KINDS, SopVisibility, make_visibility
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.sops.query import ProbeGrid


class SopPbrBase(AttachedRender):
    r"""
    .. _integrator-sop_pbr:

    SOP deferred PBR (:monosp:`sop_pbr`)
    ------------------------------------

    .. pluginparameters::

     * - envmap
       - |string|
       - Environment map file (.exr/.hdr, equirect or our octahedral EXR). Optional: by
         default the scene's ``octenvmap`` emitter lights the surfels (required then)
     * - envmap_scale, envmap_res
       - |float|, |int|
       - Scale and octahedral resolution of ``envmap`` (Default: 1, and the resolution
         of ``octenvmap``'s ``filename``)
     * - visibility
       - |string|
       - ``sops`` (needs ``probes``), ``trace`` or ``none`` (Default: sops if ``probes``
         is given, else trace)
     * - probes
       - |string|
       - Probe file written by ``comgs decompose`` / ``sops.ProbeSet.save``
     * - probe_k
       - |int|
       - Probes interpolated per shading point (Default: 8)
     * - rays
       - |int|
       - S_r, directions per shading point (Default: 256, the paper's rendering count;
         ``spp`` given to ``mi.render`` overrides it)
     * - sampling
       - |string|
       - ``mis`` (env-map + BRDF importance sampling, balance heuristic), ``uniform`` (the
         paper's training estimator) or ``cosine`` (Default: mis)
     * - decorrelate
       - |bool|
       - A random rotation of the sample set per shading point (Default: true; false
         shares one set across the image, as the paper's training estimator)
     * - min_roughness
       - |float|
       - Roughness clamp at shading time (Default: 0; MIS needs none)
     * - indirect
       - |bool|
       - Add indirect light L_in (Default: true)
     * - hide_emitters
       - |bool|
       - Black background instead of the environment seen through uncovered pixels
         (Default: false)
     * - max_hits / trace_hits
       - |int|
       - Surfels composited per camera ray / per visibility ray (Default: 32 / 8)
     * - trace_offset
       - |float|
       - Visibility ray origin offset along the normal, scene units (Default: 1 % of the
         surfels' object size)

    Output: linear RGB (RGBA when the film's ``pixel_format`` has alpha; alpha = surfel
    coverage W), colour premultiplied by W. Exactly one ``surfels`` shape carrying
    materials is shaded (other shapes are ignored).
    """

    plugin_name = "sop_pbr"

    def __init__(self, props: mi.Properties):
        type(self).__bases__[0].__init__(self, props)
        self.env = None
        if "envmap" in props:
            emprops = mi.Properties("octenvmap")
            emprops["filename"] = str(props["envmap"])
            emprops["scale"] = float(props.get("envmap_scale", 1.0))
            if "envmap_res" in props:
                emprops["resolution"] = int(props["envmap_res"])
            self.env = emitter_class()(emprops)
        self.probes_path = str(props["probes"]) if "probes" in props else None
        self.visibility_kind = str(props.get("visibility", "sops" if self.probes_path else "trace"))
        if self.visibility_kind not in KINDS:
            raise ValueError(f"sop_pbr: 'visibility' must be sops, trace or none, got "
                             f"{self.visibility_kind!r}")
        if self.visibility_kind == "sops" and not self.probes_path:
            raise ValueError("sop_pbr: visibility 'sops' needs the 'probes' file parameter")
        sampling = str(props.get("sampling", "mis"))
        if sampling not in SAMPLINGS:
            raise ValueError(f"sop_pbr: 'sampling' must be one of {', '.join(SAMPLINGS)}, got {sampling!r}")
        self.cfg = ShadingConfig(rays=int(props.get("rays", 256)), sampling=sampling,
                                 indirect=bool(props.get("indirect", True)),
                                 min_roughness=float(props.get("min_roughness", 0.0)),
                                 decorrelate=bool(props.get("decorrelate", True)))
        self.hide_emitters = bool(props.get("hide_emitters", False))
        self.max_hits = int(props.get("max_hits", 32))
        self.trace_hits = int(props.get("trace_hits", 8))
        self.trace_offset = float(props.get("trace_offset", -1.0))
        self.probe_k = int(props.get("probe_k", 8))
        self.probe_data = None
        if self.visibility_kind == "sops":
            self._load_probes(ProbeSet.load(self.probes_path))
        self._pbr = None

    # ----------------------------------------------------------------- parameters
    def _load_probes(self, probes: ProbeSet):
        self.probe_set = probes
        # interior textures [P, R, R, 4] (RGB = L_in, A = O); the border is a gather
        self.probe_data = to_jit(mi.TensorXf, probes.texture)
        self._border = octa.BorderGather(probes.count, probes.res, 4)
        self._grid = ProbeGrid(probes.positions, probes.radius)
        self._sops = SopVisibility(None, self._grid, probes.res, self.probe_k)

    def traverse(self, callback):
        if self.probe_data is not None:
            callback.put("probe_data", self.probe_data, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=[]):
        if self.probe_data is not None:
            want = (self.probe_set.count, self.probe_set.res, self.probe_set.res, 4)
            if tuple(self.probe_data.shape) != want:
                raise ValueError(f"sop_pbr: 'probe_data' must stay {want}, got {tuple(self.probe_data.shape)}")

    # ----------------------------------------------------------------- rendering
    def environment(self, scene):
        """The map that lights the surfels: ``envmap`` if given, else the scene's emitter."""
        if self.env is not None:
            return self.env
        env = scene.environment()
        if env is None or not is_octenvmap(env):
            raise ValueError("sop_pbr: the scene needs an 'octenvmap' emitter (or give the "
                             "integrator an 'envmap' file); found "
                             f"{'none' if env is None else type(env).__name__}")
        return env

    def _visibility(self, scene):
        if self.visibility_kind == "sops":
            self._sops.atlas = self._border(self.probe_data.array)
            return self._sops
        return make_visibility(self.visibility_kind, scene=scene, trace_hits=self.trace_hits,
                               trace_offset=self.trace_offset)

    def _deferred(self, scene, env, vis, cfg):
        if self._pbr is None or self._pbr.scene is not scene:
            self._pbr = DeferredPbr(scene, env, vis, cfg, self.max_hits)
        self._pbr.env, self._pbr.visibility, self._pbr.cfg = env, vis, cfg
        return self._pbr

    def shading_points(self, scene, sensor=0):
        """(ShadingPoints, geometry) of a sensor's covered pixels (an index or a sensor):
        geometry cached, materials blended from the surfels' current (attached) parameters."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        pbr = self._deferred(scene, self.environment(scene), self._visibility(scene), self.cfg)
        return pbr.shading_points(sensor)

    def render_attached(self, scene, sensor=0, seed=0, spp=0, alpha=None):
        """The image as a differentiable expression of the current parameters (no custom op)."""
        if not isinstance(sensor, int) and not isinstance(sensor, mi.Sensor):
            raise TypeError(f"sop_pbr: sensor must be an index or a Sensor, got {type(sensor).__name__}")
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        env = self.environment(scene)
        cfg = self.cfg
        if spp and int(spp) > 0 and int(spp) != cfg.rays:
            cfg = ShadingConfig(**{**cfg.__dict__, "rays": max(int(spp), 2)})
        vis = self._visibility(scene)
        pbr = self._deferred(scene, env, vis, cfg)
        self.sees_nothing = dr.width(pbr.geometry(sensor)["pix"]) == 0
        if self.sees_nothing:
            col, geo = None, pbr.geometry(sensor)    # nothing covered (e.g. a grazing view)
        else:
            pts, geo = pbr.shading_points(sensor)
            col = shade(pts, env, vis, cfg, int(seed))
        bg = None if self.hide_emitters else env.eval_world(geo["dirs"])
        if alpha is None:
            alpha = sensor.film().base_channels_count() == 4
        return pbr.compose_linear(col, geo, alpha, bg)

    def to_string(self):
        return (f"SopPbrIntegrator[visibility={self.visibility_kind}, rays={self.cfg.rays}, "
                f"sampling={self.cfg.sampling}]")


def integrator_class():
    return _make_class(mi.variant())


@functools.cache
def _make_class(variant: str):
    return variant_class("SopPbrIntegrator", SopPbrBase, mitsuba_ad_base("ADIntegrator"))


def register():
    mi.register_integrator("sop_pbr", lambda props: integrator_class()(props))
