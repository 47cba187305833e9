"""The ``surfel_gbuffer`` integrator: multi-target rendering of surfels.

Paper eq. (Multi-Target Rendering): B = Σ_i T_i α_i b_i with
b_i = {c_i, 1, d_i, n_i, a_i, r_i, m_i} and T_i = Π_{j<i} (1 − α_j), giving the
colour C, weight W, depth D, normal N, albedo A, roughness R and metallic M
buffers in one pass, plus the unbiased depth D̃ = D / W.
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi

from . import common, compositing
from .common import mitsuba_ad_base
from ..surfels.shape import variant_class

TARGETS = ("color", "weight", "depth", "depth_unbiased", "normal", "albedo", "roughness", "metallic")
_CHANNELS = {"weight": ["weight"], "depth": ["depth"], "depth_unbiased": ["depth_unbiased"],
             "normal": ["normal.X", "normal.Y", "normal.Z"],
             "albedo": ["albedo.R", "albedo.G", "albedo.B"],
             "roughness": ["roughness"], "metallic": ["metallic"]}


def parse_targets(spec: str) -> tuple[str, ...]:
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if names == ["all"]:
        return TARGETS
    bad = [s for s in names if s not in TARGETS]
    if bad or not names:
        raise ValueError(f"surfel_gbuffer: 'targets' has unknown entries {bad or [spec]}; "
                         f"choose from {', '.join(TARGETS)} or 'all'")
    return tuple(t for t in TARGETS if t in names)


class SurfelGBufferBase:
    r"""
    .. _integrator-surfel_gbuffer:

    Surfel G-buffer (:monosp:`surfel_gbuffer`)
    ------------------------------------------

    .. pluginparameters::

     * - max_hits
       - |int|
       - K, the largest number of surfels composited per ray (Default: 32)
     * - epsilon
       - |float|
       - Origin advance past each hit in scene units; ≤ 0 picks 1e-5 of the scene's
         bounding-box diagonal (Default: -1)
     * - targets
       - |string|
       - Comma-separated subset of ``color, weight, depth, depth_unbiased, normal,
         albedo, roughness, metallic`` or ``all`` (Default: all). Targets not asked
         for are not computed (no gathers, no AOV channels).
     * - background
       - |float|
       - Grey level added to the colour as T_final · background (Default: 0)

    The colour goes to the film's RGB channels (0 when not requested); the other
    targets are AOVs named ``weight``, ``depth``, ``depth_unbiased``,
    ``normal.X/Y/Z``, ``albedo.R/G/B``, ``roughness``, ``metallic``. Depth is the
    distance along the (unit) ray; normals are world-space, facing the camera.
    Use a ``box`` reconstruction filter for exact per-pixel buffers.
    All targets are differentiable w.r.t. every surfel parameter (``mi.render``
    with ``params``). Every shape of the scene must be a ``surfels`` shape.

    .. code-block:: xml

        <integrator type="surfel_gbuffer">
            <integer name="max_hits" value="32"/>
            <string name="targets" value="color,weight,depth,normal"/>
        </integrator>
    """

    def __init__(self, props: mi.Properties):
        type(self).__bases__[0].__init__(self, props)
        self.max_hits = int(props.get("max_hits", 32))
        if not 1 <= self.max_hits <= 1024:
            raise ValueError(f"surfel_gbuffer: 'max_hits' must be in 1..1024, got {self.max_hits}")
        self.epsilon = float(props.get("epsilon", -1.0))
        self.targets = parse_targets(str(props.get("targets", "all")))
        self.background = float(props.get("background", 0.0))
        if not (self.background == self.background) or self.background < 0:
            raise ValueError(f"surfel_gbuffer: 'background' must be ≥ 0, got {self.background}")

    # ---------------------------------------------------------------- AOVs
    def aov_names(self):
        return [c for t in self.targets if t != "color" for c in _CHANNELS[t]]

    def channel_slices(self, n_channels: int) -> dict:
        """Channel ranges of each target in ``mi.render``'s output tensor."""
        aovs = self.aov_names()
        first = n_channels - len(aovs)          # RGB or RGBA before the AOVs
        out = {"color": slice(0, 3)} if "color" in self.targets else {}
        c = first
        for t in self.targets:
            if t == "color":
                continue
            k = len(_CHANNELS[t])
            out[t] = slice(c, c + k)
            c += k
        return out

    def split(self, image) -> dict:
        """Split a rendered tensor [H, W, C] into {target: tensor [H, W, c]}."""
        return {k: image[:, :, s] for k, s in self.channel_slices(image.shape[2]).items()}

    # -------------------------------------------------------------- sample
    def sample(self, mode, scene, sampler, ray, δL=None, δaovs=None, state_in=None,
               active=True, **kwargs):
        """Primal: trace + composite. Backward/Forward: adjoint over the stored hits."""
        shapes = common.surfel_shapes(scene, "surfel_gbuffer")
        ray = mi.Ray3f(dr.detach(ray))
        if mode == dr.ADMode.Primal:
            eps = self.epsilon if self.epsilon > 0 else common.auto_epsilon(scene)
            hits, out, acc, T = compositing.trace_composite(
                scene, shapes, ray, self.max_hits, eps, self.targets, self.background, active)
            L = out.get("color", mi.Color3f(0.0))
            return mi.Spectrum(L), acc["weight"] > 0, self._flatten(out), (hits, acc, T)
        hits, acc, T = state_in
        if mode == dr.ADMode.Backward:
            grads = self._unflatten(δL, δaovs)
            compositing.composite_adjoint(mode, shapes, ray, hits, acc, T, self.targets,
                                          grads, self.background)
            return mi.Spectrum(0.0), acc["weight"] > 0, [], None
        tan = compositing.composite_adjoint(mode, shapes, ray, hits, acc, T, self.targets,
                                            None, self.background)
        L = tan.get("color", mi.Color3f(0.0))
        return mi.Spectrum(L), acc["weight"] > 0, self._flatten(tan), None

    def _flatten(self, out: dict) -> list:
        aovs = []
        for t in self.targets:
            if t == "color":
                continue
            v = out[t]
            aovs += [v] if isinstance(v, mi.Float) else [v[i] for i in range(3)]
        return aovs

    def _unflatten(self, δL, δaovs) -> dict:
        g, i = {}, 0
        if "color" in self.targets and δL is not None:
            g["color"] = mi.Color3f(δL)
        for t in self.targets:
            if t == "color":
                continue
            k = len(_CHANNELS[t])
            g[t] = δaovs[i] if k == 1 else mi.Vector3f(δaovs[i], δaovs[i + 1], δaovs[i + 2])
            i += k
        return g

    def to_string(self):
        return (f"SurfelGBufferIntegrator[max_hits={self.max_hits}, "
                f"targets={','.join(self.targets)}]")


def integrator_class():
    """The ``surfel_gbuffer`` class of the active variant."""
    return _make_class(mi.variant())


@functools.cache
def _make_class(variant: str):
    base = mitsuba_ad_base("RBIntegrator")
    return variant_class("SurfelGBufferIntegrator", SurfelGBufferBase, base)


def register():
    mi.register_integrator("surfel_gbuffer", lambda props: integrator_class()(props))
