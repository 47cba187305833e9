"""The ``comgs_composite`` Mitsuba integrator: reconstructed objects inserted into a
reconstructed scene (paper, "Rendering").

Per frame: one trace through every surfel shape gives per-shape-group layers
(:mod:`comgs_dr.surfels.groups`: the scene's radiance-field colour, each object's coverage
W, depth and normal, and per-hit blend weights), so depth compositing is exact per surfel
and antialiased. The scene layer is multiplied by the shadow ratio S = L_o'/L_o
(:func:`comgs_dr.shading.shadow.shadow_ratio`, L_i importance-sampled from the map lighting
the nearest object, O' from the cached shadow-region probes or traced, a map's compact sun
split off and traced per pixel (``sun_rays``), the receivers' normals blended from the shadow
probes' plane-fitted normals); each object layer
is relit by deferred PBR (:func:`comgs_dr.shading.shade.shade`) under its own map with its
own probes, whose occlusion includes the other objects'. Materials are blended from the
object shapes' (traversable) parameters, so ``mi.render`` + ``dr.backward`` give gradients
w.r.t. e.g. ``<object>.albedo``.

Passes a frame does not need are left out: the shadow pass runs only for scene pixels in
some object's shadow region, an object with no covered pixel is not shaded, no indirect
term with ``indirect=false``, no shadow pass for ``noshadow``/``paste``.
"""
from __future__ import annotations

import functools
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core import colorspace
from comgs_dr.core.cameras import camera_rays
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.variant import AttachedRender, mitsuba_ad_base, variant_class
from comgs_dr.emitters.octenvmap import emitter_class, is_octenvmap
from comgs_dr.shading.deferred import rgba_tensor
from comgs_dr.shading.shade import SAMPLINGS, ShadingConfig, ShadingPoints, shade
from comgs_dr.shading.shadow import shadow_ratio
from comgs_dr.shading.sun import split_sun
from comgs_dr.shading.sun_shadow import SunShadowMap
from comgs_dr.shading.visibility import NoVisibility, SopVisibility, TraceVisibility
from comgs_dr.sops.occlusion import region_box
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.sops.query import ProbeGrid, query
from comgs_dr.surfels.composite import surfel_shapes
from comgs_dr.surfels.edit import parse_material_spec
from comgs_dr.surfels.groups import group_gbuffer, group_materials
from comgs_dr.surfels.params import object_bounds, object_size
from comgs_dr.surfels.shape import SurfelShapeBase

VARIANTS = ("sop", "trace", "noshadow", "paste")
MIN_WEIGHT = 1e-3             # pixels where a layer covers less than this are not shaded


def is_file_property(key: str, value) -> bool:
    """Whether property ``key`` (of value ``value``) names a file the integrator reads: the
    maps, probe sets and the sky (an empty ``sky`` turns it off)."""
    if key == "sky":
        return bool(str(value))
    return key in ("shadow_probes", "envmap") or key.startswith(("envmap_", "probes_"))


def _existing_file(key: str, path: str) -> str:
    """``path`` resolved as Mitsuba resolves files (a relative path in an XML scene: against
    the XML's folder, during loading), or FileNotFoundError naming the property. Checked
    here because the files are read at the first render, where an error surfaces wrapped
    in ``mi.render``'s custom-op RuntimeError."""
    resolved = str(mi.file_resolver().resolve(path))
    if not Path(resolved).is_file():
        raise FileNotFoundError(f"comgs_composite: the '{key}' file {path!r} is not found")
    return str(Path(resolved).resolve())


class CompositeBase(AttachedRender):
    r"""
    .. _integrator-comgs_composite:

    ComGS composite (:monosp:`comgs_composite`)
    -------------------------------------------

    .. pluginparameters::

     * - scene_shape
       - |string|
       - Id of the ``surfels`` shape holding the reconstructed scene (Default: ``scene``);
         every other ``surfels`` shape is an inserted object (with materials)
     * - variant
       - |string|
       - ``sop`` (shadows from cached probes), ``trace`` (shadows and object occlusion
         traced per frame), ``noshadow`` (objects relit, no shadow on the scene) or
         ``paste`` (objects' step-1 radiance, no relighting, no shadows) (Default: sop when
         ``shadow_probes`` is given, else trace)
     * - envmap, envmap_<id>
       - |string|
       - Map lighting every object / object ``<id>`` (equirect Z-up or our octahedral EXR;
         Default: the scene's ``octenvmap`` emitter)
     * - probes_<id>
       - |string|
       - World-space probe file of object ``<id>`` (its SOPs placed, occlusion by the other
         objects included; written by ``comgs compose``). Without it the object's
         occlusion is traced
     * - shadow_probes
       - |string|
       - Shadow-region probes with cached occlusion (``comgs compose``); needed by ``sop``
     * - material_<id>
       - |string|
       - Material override of object ``<id>``, e.g. ``albedo=0.8,0.1,0.1,roughness=0.3``
     * - rays, shadow_rays
       - |int|
       - S_r for relighting objects / for the shadow ratio (Default: 256 / 256)
     * - sampling
       - |string|
       - Estimator of the objects' shading: ``mis``, ``uniform`` or ``cosine`` (Default: mis)
     * - indirect
       - |bool|
       - Indirect light L_in on objects from their probes (Default: true)
     * - region_factor
       - |float|
       - Shadow region = object bounds × this (Default: 6, as the probes)
     * - probe_k, max_hits, trace_hits
       - |int|
       - Probes interpolated per point / surfels composited per camera ray / per traced
         occlusion ray (Default: 8 / 32 / 32)
     * - sun_rays
       - |int|
       - Shadow rays per scene pixel toward the dominant compact source of an object's map
         (:func:`comgs_dr.shading.sun.split_sun`: a sun giving ≥ 3 % of the irradiance
         facing it); the probes (``sop``) keep the rest of the map. 0: the probes carry
         the whole map (Default: 16)
     * - sun_map_res
       - |int|
       - ``sop``: the sun rays look up a ``res``² shadow map traced once toward the sun
         (:class:`comgs_dr.shading.sun_shadow.SunShadowMap`); 0: they are traced per pixel
         (exact, 2–3× a frame's time). ``trace`` always traces them (Default: 512)
     * - shadow_normals
       - |string|
       - Normals of the scene's shadow receivers: ``probes`` (blended from the shadow-region
         probes' plane-fitted normals, ``sops.occlusion.plane_normals``; ``depth`` where no
         probe is in reach or none are given), ``depth`` (from the scene layer's rendered
         depth, ``GroupBuffers.depth_normals``; the surfels' own where it has an edge) or
         ``surfel`` (Default: probes)
     * - colour_space
       - |string|
       - Space of the radiance fields' colour (Default: srgb)
     * - sky
       - |string|
       - Step 1's learned background of the scene (``background.exr``, octahedral, in the
         radiance field's colour space), shown where nothing covers a pixel
         (Default: none: black; an empty string turns a recorded sky off)

    Output: linear RGB (RGBA with an alpha film: alpha = total coverage).
    """

    plugin_name = "comgs_composite"

    def __init__(self, props: mi.Properties):
        type(self).__bases__[0].__init__(self, props)
        self.scene_id = str(props.get("scene_shape", "scene"))
        keys = list(props.keys())
        files = {k: _existing_file(k, str(props[k])) for k in keys
                 if is_file_property(k, props[k])}
        self.shadow_path = files.get("shadow_probes")
        self.variant = str(props.get("variant", "sop" if self.shadow_path else "trace"))
        if self.variant not in VARIANTS:
            raise ValueError(f"comgs_composite: 'variant' must be one of {', '.join(VARIANTS)}, "
                             f"got {self.variant!r}")
        if self.variant == "sop" and not self.shadow_path:
            raise ValueError("comgs_composite: variant 'sop' needs the 'shadow_probes' file")
        self.env_files = {k[7:]: files[k] for k in keys if k.startswith("envmap_")}
        self.default_env = files.get("envmap")
        self.probe_files = {k[7:]: files[k] for k in keys if k.startswith("probes_")}
        self.materials = {k[9:]: parse_material_spec(str(props[k]))
                          for k in keys if k.startswith("material_")}
        if self.materials and self.variant == "paste":
            raise ValueError(f"comgs_composite: variant 'paste' shows the objects' captured "
                             f"radiance, so material overrides "
                             f"({', '.join('material_' + n for n in self.materials)}) would be "
                             f"ignored; use sop, trace or noshadow")
        sampling = str(props.get("sampling", "mis"))
        if sampling not in SAMPLINGS:
            raise ValueError(f"comgs_composite: 'sampling' must be one of {', '.join(SAMPLINGS)}, "
                             f"got {sampling!r}")
        self.cfg = ShadingConfig(rays=int(props.get("rays", 256)), sampling=sampling,
                                 indirect=bool(props.get("indirect", True)))
        self.shadow_rays = int(props.get("shadow_rays", 256))
        self.sun_rays = int(props.get("sun_rays", 16))
        if self.sun_rays < 0:
            raise ValueError(f"comgs_composite: sun_rays must be ≥ 0, got {self.sun_rays}")
        self.sun_map_res = int(props.get("sun_map_res", 512))
        if self.sun_map_res != 0 and self.sun_map_res < 2:
            raise ValueError(f"comgs_composite: sun_map_res must be 0 (trace) or ≥ 2, got "
                             f"{self.sun_map_res}")
        self.region_factor = float(props.get("region_factor", 6.0))
        self.probe_k = int(props.get("probe_k", 8))
        self.max_hits = int(props.get("max_hits", 32))
        self.trace_hits = int(props.get("trace_hits", 32))
        self.shadow_normals = str(props.get("shadow_normals", "probes"))
        if self.shadow_normals not in ("probes", "depth", "surfel"):
            raise ValueError(f"comgs_composite: shadow_normals must be probes, depth or "
                             f"surfel, got {self.shadow_normals!r}")
        self.colour_space = str(props.get("colour_space", "srgb"))
        if self.colour_space not in ("srgb", "linear"):
            raise ValueError(f"comgs_composite: colour_space must be srgb or linear, got "
                             f"{self.colour_space!r}")
        self.sky_path = files.get("sky")                                  # "": off
        self._state = None
        self._geo = {}

    # ----------------------------------------------------------------- setup
    def _env(self, scene, name):
        path = self.env_files.get(name, self.default_env)
        if path is not None:
            props = mi.Properties("octenvmap")
            props["filename"] = path
            return emitter_class()(props)
        env = scene.environment()
        if env is None or not is_octenvmap(env):
            raise ValueError(f"comgs_composite: no map lights object {name!r}: give "
                             f"'envmap_{name}' or 'envmap', or an 'octenvmap' emitter")
        return env

    def _setup(self, scene):
        if self._state is not None and self._state["scene"] is scene:
            return self._state
        shapes = surfel_shapes(scene, "comgs_composite")
        ids = [s.id() for s in shapes]
        if self.scene_id not in ids:
            raise ValueError(f"comgs_composite: no surfels shape with id {self.scene_id!r} "
                             f"(the scene); shapes: {', '.join(ids)}")
        slot_scene = ids.index(self.scene_id)
        objects = [j for j in range(len(shapes)) if j != slot_scene]
        unknown = (set(self.env_files) | set(self.probe_files) | set(self.materials)) \
            - {ids[j] for j in objects}
        if unknown:
            raise ValueError(f"comgs_composite: parameters name unknown objects "
                             f"{sorted(unknown)}; objects: {[ids[j] for j in objects]}")
        groups = [0] * len(shapes)
        st = {"scene": scene, "shapes": shapes, "slot_scene": slot_scene, "objects": []}
        for g, j in enumerate(objects, start=1):
            groups[j] = g
            name, p = ids[j], shapes[j].params
            lo, hi = object_bounds(p)
            obj = {"name": name, "slot": j, "group": g, "env": self._env(scene, name),
                   "box": region_box(lo, hi, self.region_factor), "centre": (lo + hi) / 2,
                   "size": float(np.linalg.norm(hi - lo)), "vis": None,
                   "material": self.materials.get(name), "sun": None}
            if self.sun_rays and self.variant in ("sop", "trace"):
                obj["sun"] = split_sun(obj["env"])
            if name in self.probe_files and self.variant != "trace":
                pr = ProbeSet.load(self.probe_files[name])
                if pr.texture is None:
                    raise ValueError(f"comgs_composite: probes of {name!r} are not baked")
                obj["vis"] = SopVisibility(pr.atlas(), ProbeGrid(pr.positions, pr.radius),
                                           pr.res, self.probe_k)
            st["objects"].append(obj)
        st["groups"] = groups
        if self.sky_path is not None:
            props = mi.Properties("octenvmap")
            props["filename"] = self.sky_path
            st["sky"] = emitter_class()(props)
        if self.shadow_path and self.variant in ("sop", "trace"):
            sp = ProbeSet.load(self.shadow_path)
            st["shadow_grid"] = (ProbeGrid(sp.positions, sp.radius),
                                 to_jit(mi.Vector3f, np.asarray(sp.normals, np.float32).T))
            if self.variant == "sop":
                if sp.texture is None:
                    raise ValueError(f"comgs_composite: shadow probes {self.shadow_path} are "
                                     f"not baked")
                st["shadow_vis"] = SopVisibility(sp.atlas(), st["shadow_grid"][0], sp.res,
                                                 self.probe_k)
        sun_map = self.variant == "sop" and self.sun_map_res > 0
        needs_trace = self.variant == "trace" or any(
            o["vis"] is None or (o["sun"] is not None and not sun_map) for o in st["objects"]) \
            and self.variant != "paste"
        suns = [o for o in st["objects"] if o["sun"] is not None]
        occ_scene = None
        if (needs_trace or suns) and objects:
            occ_scene = mi.load_dict({"type": "scene", **{
                ids[j]: SurfelShapeBase.from_params(shapes[j].params, id=ids[j])
                for j in objects}})
        if needs_trace and objects:
            off = 0.01 * max(object_size(shapes[j].params) for j in objects)
            tv = TraceVisibility(occ_scene, off, self.trace_hits, self.colour_space)
            st["trace_vis"] = tv
            for o in st["objects"]:
                if o["vis"] is None:
                    o["vis"] = tv
        for o in suns:
            o["sun_vis"] = st["trace_vis"] if not sun_map else self._sun_map(
                occ_scene, o["sun"].direction, [shapes[j].params for j in objects])
        self._state = st
        self._geo.clear()
        return st

    def _sun_map(self, occ_scene, direction, params):
        """A :class:`SunShadowMap` over every object's surfels toward ``direction``."""
        bounds = [object_bounds(p) for p in params]
        lo = np.min([b[0] for b in bounds], 0)
        hi = np.max([b[1] for b in bounds], 0)
        radius = 0.5 * float(np.linalg.norm(hi - lo)) * 1.1 + 1e-6
        return SunShadowMap(occ_scene, direction, (lo + hi) / 2, radius, self.sun_map_res,
                            self.trace_hits)

    def _buffers(self, scene, sensor, st):
        version = tuple(getattr(s, "geometry_version", 0) for s in st["shapes"])
        pose = np.asarray(sensor.world_transform().matrix, np.float32).tobytes()
        key = (sensor.ptr, pose, tuple(sensor.film().crop_size()), version)
        if key not in self._geo:
            self._geo.clear()
            colour = [0] + ([o["group"] for o in st["objects"]] if self.variant == "paste" else [])
            self._geo[key] = group_gbuffer(scene, sensor, st["groups"], self.max_hits, colour)
        return self._geo[key]

    # ----------------------------------------------------------------- passes
    def _linear(self, c, W):
        return (colorspace.unpremultiplied_to_linear(c, W) if self.colour_space == "srgb"
                else mi.Color3f(dr.maximum(c, 0.0)))

    def _shadow(self, buf, st, seed):
        """S per pixel [H*W] (ones outside every shadow region), or None (no pass)."""
        if self.variant not in ("sop", "trace") or not st["objects"]:
            return None
        Ws = buf.weight[0]
        h, w = buf.shape
        x_all, n_all, _ = buf.points(0, dr.arange(mi.UInt32, h * w))
        inside = mi.Bool(False)
        best, best_d = mi.UInt32(0), dr.full(mi.Float, np.inf, h * w)
        for i, o in enumerate(st["objects"]):
            lo, hi = o["box"]
            inb = dr.all((x_all >= mi.Point3f(*map(float, lo)))
                         & (x_all <= mi.Point3f(*map(float, hi))))
            inside |= inb
            d = dr.squared_norm(x_all - mi.Point3f(*map(float, o["centre"])))
            closer = inb & (d < best_d)
            best, best_d = dr.select(closer, i, best), dr.select(closer, d, best_d)
        vis = st["shadow_vis"] if self.variant == "sop" else st["trace_vis"]
        S = dr.full(mi.Color3f, 1.0, h * w)
        n_depth = buf.depth_normals(0)[0] if self.shadow_normals != "surfel" else None
        for i, o in enumerate(st["objects"]):
            pix = dr.compress((Ws > MIN_WEIGHT) & inside & (best == i))
            if dr.width(pix) == 0:
                continue
            x, n, _ = buf.points(0, pix)
            if n_depth is not None:
                n = dr.gather(mi.Vector3f, n_depth, pix)
            if self.shadow_normals == "probes" and "shadow_grid" in st:
                n = _probe_normals(st["shadow_grid"], x, n, self.probe_k)
            s = shadow_ratio(x, n, o["env"], vis, self.shadow_rays, seed + 7919 * (i + 1),
                             sun=o["sun"], sun_visibility=o.get("sun_vis"),
                             sun_rays=self.sun_rays)
            dr.scatter(S, s, pix)
        return S

    def _object_colour(self, buf, st, o, pix, seed, cfg):
        if self.variant == "paste":
            W = dr.gather(mi.Float, buf.weight[o["group"]], pix)
            return self._linear(dr.gather(mi.Color3f, buf.colour[o["group"]], pix), W) \
                / dr.maximum(W, 1e-6)
        shape = st["shapes"][o["slot"]]
        x, n, wo = buf.points(o["group"], pix)
        mats = group_materials(buf, pix, o["slot"], shape.params)
        e = o["material"]
        if e is not None:
            if e.albedo is not None:
                mats["albedo"] = mi.Color3f(*e.albedo)
            if e.albedo_scale is not None:
                mats["albedo"] = dr.clip(mats["albedo"] * mi.Color3f(*e.albedo_scale), 0.0, 1.0)
            if e.roughness is not None:
                mats["roughness"] = mi.Float(e.roughness)
            if e.metallic is not None:
                mats["metallic"] = mi.Float(e.metallic)
        pts = ShadingPoints(position=x, normal=n, wo=wo, **mats)
        vis = o["vis"] if o["vis"] is not None else NoVisibility()
        return shade(pts, o["env"], vis, cfg, seed)

    def render_attached(self, scene, sensor=0, seed=0, spp=0):
        """The composite as a differentiable expression of the objects' materials."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        st = self._setup(scene)
        buf = self._buffers(scene, sensor, st)
        cfg = self.cfg
        if spp and int(spp) > 0 and int(spp) != cfg.rays:
            cfg = ShadingConfig(**{**cfg.__dict__, "rays": max(int(spp), 2)})
        h, w = buf.shape
        Ws = buf.weight[0]
        img = self._linear(buf.colour[0], Ws)                                # [H*W]
        if "sky" in st:                            # T_final · sky, as step 1 rendered it
            cover = dr.clip(sum(buf.weight[1:], Ws), 0.0, 1.0)
            dirs, _ = camera_rays(sensor, w, h)
            sky = st["sky"].eval_world(mi.Vector3f(dr.unravel(mi.Vector3f, dirs.array)))
            img = img + (1.0 - cover) * self._linear(dr.clip(sky, 0.0, 1.0), mi.Float(1.0))
        S = self._shadow(buf, st, int(seed))
        if S is not None:
            # the shadow darkens the whole pixel step 1 fitted, its T_final · sky included: a
            # ground a few percent transparent showed the bright sky through its shadow
            # (demo: S 0.50 in the truth's shadow pixels, the image 0.56 of the unshadowed)
            img = img * S
        self.sees_nothing = True    # no object pixel: nothing here depends on materials
        for o in st["objects"]:
            Wg = buf.weight[o["group"]]
            pix = dr.compress(Wg > MIN_WEIGHT)
            if dr.width(pix) == 0:
                continue            # outside the view or hidden: no shading pass
            self.sees_nothing = False
            c = self._object_colour(buf, st, o, pix, int(seed) + 104729 * o["group"], cfg)
            layer = dr.zeros(mi.Color3f, h * w)
            dr.scatter(layer, dr.gather(mi.Float, Wg, pix) * c, pix)
            img = img + layer
        if sensor.film().base_channels_count() == 4:
            cover = dr.clip(sum(buf.weight[1:], Ws), 0.0, 1.0)
            return rgba_tensor(img, cover, h, w)
        return mi.TensorXf(dr.ravel(img), shape=(h, w, 3))

    def to_string(self):
        return f"CompositeIntegrator[variant={self.variant}, rays={self.cfg.rays}]"


def _probe_normals(grid, x, n, k: int):
    """Receivers' normals [P] blended from the ``k`` nearest shadow probes' normals (eq.-knn
    weights); ``n`` where no probe is within the query radius or the blend vanishes."""
    g, normals = grid
    knn = query(g, x, n, k)
    acc = dr.zeros(mi.Vector3f, dr.width(x))
    for j in range(k):
        slot = dr.arange(mi.UInt32, dr.width(x)) * k + j
        w = dr.gather(mi.Float, knn.weight, slot)
        acc += w * dr.gather(mi.Vector3f, normals, dr.gather(mi.UInt32, knn.index, slot))
    ok = ~knn.fallback & (dr.norm(acc) > 0.5)
    return dr.select(ok, dr.normalize(acc), n)


def integrator_class():
    return _make_class(mi.variant())


@functools.cache
def _make_class(variant: str):
    return variant_class("CompositeIntegrator", CompositeBase, mitsuba_ad_base("ADIntegrator"))


def register():
    mi.register_integrator("comgs_composite", lambda props: integrator_class()(props))
