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

from comgs_dr.core.variant import mitsuba_ad_base, variant_class
from comgs_dr.surfels import composite, raster

METHODS = ("auto", "trace", "raster")
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
       - K, the hit-buffer slots per ray and pass (Default: 32)
     * - max_passes
       - |int|
       - Rays whose K slots are full while their transmittance is still
         ≥ 1e-4 are walked again for the next K hits behind, up to this many passes, so
         every surfel on the ray is composited as in 2DGS (Default: 16; 1: only the
         first K hits, the rest dropped); traced rays continue from their last hit the
         same way. The share of rays still open after the last pass is kept in
         ``stopped_early``
     * - epsilon
       - |float|
       - Origin advance past each hit in scene units; ≤ 0 picks 1/200 of the
         surfels' proxy depth jitter (:func:`comgs_dr.surfels.composite.auto_epsilon`);
         every step also advances at least ~4 float32 ulps of the origin (Default: -1)
     * - targets
       - |string|
       - Comma-separated subset of ``color, weight, depth, depth_unbiased, normal,
         albedo, roughness, metallic`` or ``all`` (Default: all). Targets not asked
         for are not computed (no gathers, no AOV channels).
     * - jitter
       - |bool|
       - Random sub-pixel positions at spp = 1 (Default: false: rays through pixel
         centres, deterministic buffers as a rasteriser gives; spp > 1 always jitters)
     * - background
       - |float|
       - Grey level added to the colour as T_final · background (Default: 0)
     * - env_background
       - |bool|
       - Add T_final · L_e(d) of the scene's environment emitter (any Mitsuba
         emitter, e.g. ``octenvmap`` or ``envmap``) instead of the grey ``background``:
         a sky / far-field model behind the surfels. Differentiable w.r.t. the
         emitter's parameters too (Default: false; ignored without an environment)
     * - method
       - |string|
       - How camera rays find their hits: ``raster`` bins the surfels' ±3σ quads into
         16×16 pixel tiles and walks each pixel's tile list front to back
         (:mod:`comgs_dr.surfels.raster`; pinhole ``perspective`` sensors only),
         ``trace`` re-traces the proxy quads once per hit (any sensor), ``auto``
         rasterises for perspective sensors and traces otherwise (Default: auto).
         Both give the same hit lists up to ties, composited by the same code.

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
        self.max_passes = int(props.get("max_passes", 16))
        if not 1 <= self.max_passes <= 256:
            raise ValueError(f"surfel_gbuffer: 'max_passes' must be in 1..256, got "
                             f"{self.max_passes}")
        self.stopped_early = 0.0     # share of rays still open after the last render's walk
        self.epsilon = float(props.get("epsilon", -1.0))
        self.targets = parse_targets(str(props.get("targets", "all")))
        self.jitter = bool(props.get("jitter", False))
        self.method = str(props.get("method", "auto"))
        if self.method not in METHODS:
            raise ValueError(f"surfel_gbuffer: 'method' must be one of {', '.join(METHODS)}, "
                             f"got {self.method!r}")
        self._raster_ctx = None
        self._cache_key, self._primal_cache = None, None
        self.background = float(props.get("background", 0.0))
        if not (self.background == self.background) or self.background < 0:
            raise ValueError(f"surfel_gbuffer: 'background' must be ≥ 0, got {self.background}")
        self.env_background = bool(props.get("env_background", False))

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
        shapes = composite.surfel_shapes(scene, "surfel_gbuffer")
        ray = mi.Ray3f(dr.detach(ray))
        env = self._environment(scene)
        if mode == dr.ADMode.Primal:
            bg = self.background if env is None else _env_radiance(env, ray, active)
            ctx = self._raster_ctx
            if ctx is not None and dr.width(ctx[1].x) == dr.width(ray.d):
                hits, still_open = raster.find_all_hits(shapes, ctx[0], ray, ctx[1], self.max_hits,
                                                        active, self.max_passes)
                self.stopped_early = float(still_open.mean()) if still_open.size else 0.0
                out, acc, T = composite.composite_hits(shapes, ray, hits, self.targets, bg)
            else:
                eps = self.epsilon if self.epsilon > 0 else composite.auto_epsilon(scene, shapes)
                hits, out, acc, T = composite.trace_composite(
                    scene, shapes, ray, self.max_hits, eps, self.targets, bg, active,
                    self.max_passes)
                self.stopped_early = float(hits.still_open.mean()) if hits.still_open.size else 0.0
            L = out.get("color", mi.Color3f(0.0))
            state = (hits, acc, T, bg)
            self._primal_cache = (self._cache_key, state) if self._cache_key is not None else None
            return mi.Spectrum(L), acc["weight"] > 0, self._flatten(out), state
        hits, acc, T, bg = state_in
        if mode == dr.ADMode.Backward:
            grads = self._unflatten(δL, δaovs)
            composite.composite_adjoint(mode, shapes, ray, hits, acc, T, self.targets,
                                          grads, bg)
            if env is not None and "color" in grads:        # ∂(T_final · L_e)/∂(emitter)
                with dr.resume_grad():
                    obj = dr.sum(grads["color"] * T * _env_radiance(env, ray, active, ad=True))
                    dr.backward_from(obj, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
            return mi.Spectrum(0.0), acc["weight"] > 0, [], None
        tan = composite.composite_adjoint(mode, shapes, ray, hits, acc, T, self.targets,
                                            None, bg)
        if env is not None and "color" in tan:
            with dr.resume_grad():
                Le = _env_radiance(env, ray, active, ad=True)
                tan["color"] = tan["color"] + T * mi.Color3f(dr.forward_to(
                    Le, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad))
        L = tan.get("color", mi.Color3f(0.0))
        return mi.Spectrum(L), acc["weight"] > 0, self._flatten(tan), None

    def _environment(self, scene):
        """The scene's environment emitter when ``env_background`` asks for it and the
        colour is rendered, else None (the grey ``background`` applies)."""
        if not self.env_background or "color" not in self.targets:
            return None
        return scene.environment()

    def sample_rays(self, scene, sensor, sampler):
        """Camera rays, one per sample: through pixel centres unless ``jitter`` or spp > 1.

        Returns (ray, weight, splatting position) like Mitsuba's ADIntegrator.
        Deterministic rays make the primal and the derivative passes of
        ``mi.render`` (which use different seeds) see the same G-buffer.
        """
        film = sensor.film()
        size = film.crop_size()
        spp = sampler.sample_count()
        idx = dr.arange(mi.UInt32, size[0] * size[1] * spp) // spp
        pix = mi.Vector2u(idx % size[0], idx // size[0]) + mi.Vector2u(film.crop_offset())
        offset = sampler.next_2d() if (self.jitter or spp > 1) else mi.Vector2f(0.5)
        pos_f = mi.Vector2f(pix) + offset
        # projective sensors map sample2 ∈ [0, 1]² onto the crop window (as mi.render)
        crop0, crop = mi.ScalarVector2f(film.crop_offset()), mi.ScalarVector2f(size)
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Vector2f(0.5)
        with dr.resume_grad():
            ray, weight = sensor.sample_ray_differential(
                time=sensor.shutter_open(), sample1=sampler.next_1d() if mi.is_spectral else 0.0,
                sample2=(pos_f - crop0) / crop, sample3=aperture)
        splat = mi.Vector2f(pix) if film.rfilter().is_box_filter() else pos_f
        self._raster_ctx = (sensor, pix) if self._rasterise(sensor) else None
        return ray, weight, splat

    def _rasterise(self, sensor) -> bool:
        """Whether camera rays of ``sensor`` find their hits by tile rasterisation."""
        if self.method == "trace":
            return False
        if raster.is_pinhole(sensor):
            return True
        if self.method == "raster":
            raise raster.NotPinhole(f"surfel_gbuffer: method='raster' needs a pinhole "
                                    f"'perspective' sensor, got {sensor.class_name()}; "
                                    "use method='trace' or 'auto'")
        return False

    # Mitsuba 3.9.1's RBIntegrator multiplies AOV samples by the (Spectrum) ray
    # weight before ``ImageBlock.put``, which then rejects the list whenever AOVs
    # exist; both derivative renders are therefore implemented here with the
    # scalar weight of RGB rays.
    def _splat(self, film, pos, rgb, valid, aovs, weight):
        block = film.create_block()
        w = mi.Float(weight[0]) if dr.size_v(weight) > 1 else mi.Float(weight)
        ones = dr.full(mi.Float, 1.0, dr.width(pos))
        rgb = mi.Color3f(rgb) * w
        alpha = [dr.select(valid, 1.0, 0.0)] if mi.has_flag(film.flags(), mi.FilmFlags.Alpha) else []
        block.put(pos, [rgb.x, rgb.y, rgb.z, *alpha, ones, *[a * w for a in aovs]])
        film.put_block(block)
        return film.develop()

    # The primal pass of ``mi.render`` and the derivative pass would trace the same
    # rays twice. With deterministic rays (spp = 1, no jitter) the hit buffer of the
    # last primal render is reused when sensor and surfel versions are unchanged.
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        s = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        self._cache_key = self._state_key(scene, s, spp)
        try:
            return type(self).__bases__[0].render(self, scene, s, seed, spp, develop, evaluate)
        finally:
            self._cache_key = None

    def _state_key(self, scene, sensor, spp):
        n = spp if spp > 0 else sensor.sampler().sample_count()
        if self.jitter or n != 1:
            return None
        shapes = composite.surfel_shapes(scene, "surfel_gbuffer")
        m = sensor.world_transform().matrix
        pose = tuple(float(m[i][j][0]) if dr.is_array_v(m[i][j]) else float(m[i][j])
                     for i in range(4) for j in range(4))
        return (id(scene), id(sensor), pose, tuple(sensor.film().crop_size()),
                tuple(sensor.film().crop_offset()), tuple((id(s), s.version) for s in shapes))

    def _cached_state(self, scene, sensor, spp):
        c = getattr(self, "_primal_cache", None)
        if c is None or c[0] != self._state_key(scene, sensor, spp):
            return None
        return c[1]

    def _derivative_setup(self, scene, sensor, seed, spp):
        """(sensor, sampler, spp, ray, weight, pos) of a derivative render (no AD)."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        sampler, spp = self.prepare(sensor, seed, spp, self.aov_names())
        ray, weight, pos = self.sample_rays(scene, sensor, sampler)
        return sensor, sampler, spp, ray, weight, pos

    def _primal_state(self, scene, sensor, sampler, spp, ray):
        """Hit buffer + accumulated buffers: cached from the primal render, else traced."""
        state = self._cached_state(scene, sensor, spp)
        if state is None:
            _, _, _, state = self.sample(dr.ADMode.Primal, scene, sampler.clone(), ray,
                                         active=mi.Bool(True))
        return state

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        """Forward-mode derivative image (tangents of every channel)."""
        with dr.suspend_grad():
            sensor, sampler, spp, ray, weight, pos = self._derivative_setup(scene, sensor, seed, spp)
            state = self._primal_state(scene, sensor, sampler, spp, ray)
            δL, valid, δaovs, _ = self.sample(dr.ADMode.Forward, scene, sampler, ray,
                                              state_in=state, active=mi.Bool(True))
            return self._splat(sensor.film(), pos, δL, valid, δaovs, weight)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        """Reverse mode: image adjoint → per-sample adjoints → surfel parameter gradients."""
        with dr.suspend_grad():
            sensor, sampler, spp, ray, weight, pos = self._derivative_setup(scene, sensor, seed, spp)
            film = sensor.film()
            n = dr.width(pos)
            with dr.resume_grad():   # adjoint of splatting + development
                L = dr.full(mi.Color3f, 1.0, n)
                aovs = [dr.full(mi.Float, 1.0, n) for _ in self.aov_names()]
                dr.enable_grad(L, aovs)
                image = self._splat(film, pos, L, mi.Bool(True), aovs, weight)
                dr.set_grad(image, grad_in)
                dr.enqueue(dr.ADMode.Backward, image)
                dr.traverse(dr.ADMode.Backward)
                δL, δaovs = dr.grad(L), [dr.grad(a) for a in aovs]
            film.clear()
            state = self._primal_state(scene, sensor, sampler, spp, ray)
            self.sample(dr.ADMode.Backward, scene, sampler, ray, δL=δL, δaovs=δaovs,
                        state_in=state, active=mi.Bool(True))
            dr.eval()

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
        return (f"SurfelGBufferIntegrator[max_hits={self.max_hits}, method={self.method}, "
                f"targets={','.join(self.targets)}]")


def _env_radiance(env, ray, active, ad: bool = False):
    """L_e along the rays' directions (Mitsuba's miss convention: si.wi = −d), detached
    unless ``ad``."""
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ray.d))
    si.wi = -ray.d
    if ad:
        return mi.Color3f(env.eval(si, active))
    with dr.suspend_grad():
        Le = mi.Color3f(env.eval(si, active))
        dr.eval(Le)
    return Le


def integrator_class():
    """The ``surfel_gbuffer`` class of the active variant."""
    return _make_class(mi.variant())


@functools.cache
def _make_class(variant: str):
    base = mitsuba_ad_base("RBIntegrator")
    return variant_class("SurfelGBufferIntegrator", SurfelGBufferBase, base)


def register():
    mi.register_integrator("surfel_gbuffer", lambda props: integrator_class()(props))
