"""The ``sop_pbr`` Mitsuba integrator: deferred PBR of relightable surfels.

Renders through :class:`comgs_dr.shading.deferred.DeferredPbr` (G-buffers → shading points
→ env map + SOP/trace visibility, paper "Deferred Physically Based Rendering").
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi

from comgs_dr.core.variant import mitsuba_ad_base, variant_class
from comgs_dr.lighting.envmap import OctEnvmap
from comgs_dr.shading.deferred import DeferredPbr
from comgs_dr.shading.shade import ShadingConfig
from comgs_dr.shading.visibility import KINDS, make_visibility


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
       - Visibility ray origin offset along the normal, scene units (Default: 1 % of the
         surfels' object size, as in step 2)

    Renders linear RGB (coverage-premultiplied over a black background). Every shape must
    be a ``surfels`` shape carrying materials. Only the primal is implemented: optimise
    with ``comgs decompose`` (which differentiates :class:`DeferredPbr`).
    """

    def __init__(self, props: mi.Properties):
        type(self).__bases__[0].__init__(self, props)
        if "envmap" not in props:
            raise ValueError("sop_pbr: the 'envmap' parameter (a file name) is required")
        self.env = OctEnvmap.from_file(str(props["envmap"]), int(props.get("envmap_res", 256)),
                                       float(props.get("envmap_scale", 1.0)))
        self.probes_path = str(props["probes"]) if "probes" in props else None
        self.visibility_kind = str(props.get("visibility", "sops" if self.probes_path else "trace"))
        if self.visibility_kind not in KINDS:
            raise ValueError(f"sop_pbr: 'visibility' must be sops, trace or none, got "
                             f"{self.visibility_kind!r}")
        if self.visibility_kind == "sops" and not self.probes_path:
            raise ValueError("sop_pbr: visibility 'sops' needs the 'probes' file parameter")
        self.cfg = ShadingConfig(rays=int(props.get("rays", 256)),
                                 indirect=bool(props.get("indirect", True)))
        self.max_hits = int(props.get("max_hits", 32))
        self.trace_hits = int(props.get("trace_hits", 8))
        self.trace_offset = float(props.get("trace_offset", -1.0))
        self._sops = None

    def _visibility(self, scene):
        if self.visibility_kind == "sops":      # the probe file is read and indexed once
            if self._sops is None:
                self._sops = make_visibility("sops", probes=self.probes_path)
            return self._sops
        return make_visibility(self.visibility_kind, scene=scene, trace_hits=self.trace_hits,
                               trace_offset=self.trace_offset)

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
                                  "comgs_dr.shading.deferred.DeferredPbr (see comgs_dr.stages.decompose)")

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
