"""The ``surfel_gbuffer`` integrator: multi-target rendering of surfels.

Paper eq. (Multi-Target Rendering): B = Σ_i T_i α_i b_i with
b_i = {c_i, 1, d_i, n_i, a_i, r_i, m_i} and T_i = Π_{j<i} (1 − α_j), giving the
colour C, weight W, depth D, normal N, albedo A, roughness R and metallic M
buffers in one pass, plus the unbiased depth D̃ = D / W.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..surfels import kernel as Kn
from . import common

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


class SurfelGBufferIntegrator(mi.ad.common.ADIntegrator):
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
        super().__init__(props)
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
    def sample(self, mode, scene, sampler, ray, active, **kwargs):
        shapes = common.surfel_shapes(scene, "surfel_gbuffer")
        eps = self.epsilon if self.epsilon > 0 else common.auto_epsilon(scene)
        ray = mi.Ray3f(ray)
        hits = common.trace_hits(scene, shapes, ray, self.max_hits, eps, active)
        buf = composite(shapes, ray, hits, self.targets, self.background)
        aovs = []
        for t in self.targets:
            if t == "color":
                continue
            v = buf[t]
            aovs += [v] if isinstance(v, mi.Float) else [v[i] for i in range(3)]
        L = buf.get("color", mi.Color3f(0.0))
        return mi.Spectrum(L), buf["weight_all"] > 0, aovs, None

    def to_string(self):
        return (f"SurfelGBufferIntegrator[max_hits={self.max_hits}, "
                f"targets={','.join(self.targets)}]")


def composite(shapes, ray, hits: common.HitBuffer, targets, background=0.0) -> dict:
    """Front-to-back alpha blending of the requested targets (differentiable).

    Returns {target: value} for ``targets`` plus ``weight_all`` (W, always).
    """
    need = set(targets)
    R = dr.width(hits.count)
    T = dr.full(mi.Float, 1.0, R)
    acc = {"weight": mi.Float(0.0)}
    if "color" in need:
        acc["color"] = mi.Color3f(0.0)
    if need & {"depth", "depth_unbiased"}:
        acc["depth"] = mi.Float(0.0)
    if "normal" in need:
        acc["normal"] = mi.Vector3f(0.0)
    mats = [m for m in ("albedo", "roughness", "metallic") if m in need]
    for m in mats:
        acc[m] = mi.Color3f(0.0) if m == "albedo" else mi.Float(0.0)
    sh_K = [s.params.sh_coeffs for s in shapes]
    for k in range(hits.K):
        index, slot, valid = hits.slot(k)
        smp = common.eval_surfel(shapes, slot, index, ray, valid)
        w = T * smp.alpha                                   # T_i α_i
        acc["weight"] += w
        if "depth" in acc:
            acc["depth"] += w * smp.t
        if "normal" in acc:
            acc["normal"] += w * smp.normal
        if "color" in acc:
            c = mi.Color3f(0.0)
            for j, sh in enumerate(shapes):
                m = smp.valid if len(shapes) == 1 else (smp.valid & (slot == j))
                cj = Kn.sh_color(sh.params.sh, index, sh_K[j], ray.d, m)
                c = cj if len(shapes) == 1 else dr.select(m, cj, c)
            acc["color"] += w * c
        if mats:
            g = common.gather_params(shapes, slot, index, smp.valid, mats)
            for m in mats:
                acc[m] += w * g[m]
        T = T * (1.0 - smp.alpha)
    out = {t: acc[t] for t in targets if t in acc}
    W = acc["weight"]
    if "color" in out and background > 0:
        out["color"] = out["color"] + T * background
    if "depth_unbiased" in targets:
        out["depth_unbiased"] = dr.select(W > 1e-6, acc["depth"] / dr.maximum(W, 1e-6), 0.0)
    out["weight_all"] = W
    return out


def register():
    mi.register_integrator("surfel_gbuffer", lambda props: SurfelGBufferIntegrator(props))
