"""The ``surfels`` shape plugin: 2D Gaussian surfels as a Mitsuba triangle mesh.

Each surfel is traced as one quad (2 triangles) spanning ±3σ in its tangent
plane; ``surfel = prim_index // 2``. The quad is only the ray-tracing proxy:
integrators recompute t, (u, v) and α analytically from the parameters (see
:mod:`comgs_dr.surfels.kernel`), which is what makes them differentiable.

Coplanar surfels (flat faces of ``from_mesh``, clones of densification) would
share one hit distance, and a tracer that advances the ray by ε past each hit
would find only one of them. Each proxy quad is therefore shifted along its
normal by a deterministic per-surfel offset in ±``proxy_jitter``/2
(PROXY_JITTER · bounding-box diagonal); the integrators advance by 1/200 of
that (``composite.auto_epsilon``), and all their values still come from the unshifted analytic surfel.
"""
from __future__ import annotations

import functools
import os

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.similarity import from_matrix
from comgs_dr.core.variant import is_kind, variant_class
from comgs_dr.surfels import kernel as K
from comgs_dr.surfels.io import load_ply
from comgs_dr.surfels.params import SurfelParams, field_names
from comgs_dr.surfels.transform import transform_surfels


def is_surfel_shape(obj) -> bool:
    return is_kind(obj, SurfelShapeBase)


# fields that change where rays hit (materials and colour do not: caches of hits survive them)
GEOMETRY_FIELDS = ("means", "quats", "log_scales", "opacity_logit")
PROXY_JITTER = 1e-4        # proxy depth offsets span this fraction of the surfels' bbox diagonal


class SurfelShapeBase:
    r"""
    .. _shape-surfels:

    Surfels (:monosp:`surfels`)
    ---------------------------

    .. pluginparameters::

     * - filename
       - |string|
       - PLY file of surfels (3DGS/2DGS/ComGS layouts, see ``comgs_dr.surfels.io``).
         Relative paths are resolved against Mitsuba's file resolver.
     * - to_world
       - |transform|
       - Object-to-world similarity (rotation, uniform scale, translation) applied to the
         surfels when they are loaded (positions, frames, scales, SH bands rotated exactly);
         a non-uniform scale or shear is refused. Exposed parameters are then in world space.

    Exposed parameters (``mi.traverse``), all differentiable, raw storage as in
    :class:`~comgs_dr.surfels.params.SurfelParams`: ``means``, ``quats``,
    ``log_scales``, ``opacity_logit``, ``sh``, ``albedo``, ``roughness``,
    ``metallic``. Assigning arrays of a new length to *all* of them changes the
    surfel count; the proxy quads and the BVH are rebuilt on ``update()``.

    .. code-block:: xml

        <shape type="surfels" id="object">
            <string name="filename" value="object.ply"/>
        </shape>
    """

    def __init__(self, props: mi.Properties, params: SurfelParams | None = None):
        if params is None:
            if "filename" not in props:
                raise ValueError("surfels: give <string name=\"filename\"> (a surfel PLY) "
                                 "or use SurfelShapeBase.from_params(params) from Python")
            fname = str(props["filename"])
            resolved = str(mi.file_resolver().resolve(fname))
            if not os.path.exists(resolved):
                raise FileNotFoundError(f"surfels: filename '{fname}' not found")
            params = load_ply(resolved)
        if "to_world" in props:
            m = np.array(props["to_world"].matrix, np.float64).reshape(4, 4)
            params = transform_surfels(params, from_matrix(m, props.id() or "surfels"))
        n = params.count
        if n < 1:
            raise ValueError("surfels: at least one surfel is required")
        _base(self).__init__(self, "surfels", 4 * n, 2 * n, props)
        self.params = params
        self._building = False
        self.nonfinite_count = 0
        self._rebuild()

    # ------------------------------------------------------------ interface
    @staticmethod
    def from_params(params: SurfelParams, id: str = "surfels"):
        """A ``surfels`` shape (of the active variant) holding ``params``."""
        props = mi.Properties("surfels")
        props.set_id(id)
        return shape_class()(props, params=params)

    def set_params(self, params: SurfelParams) -> None:
        """Replace all surfels (any count) and rebuild quads/BVH via the parent scene update."""
        for f in field_names():
            setattr(self.params, f, getattr(params, f))
        self._rebuild()
        self.version += 1
        self.geometry_version += 1

    def surfel_count(self) -> int:
        return self.params.count

    # -------------------------------------------------------- Mitsuba hooks
    def traverse(self, callback):
        if self._building:   # internal: expose the mesh buffers to rewrite them
            _base(self).traverse(self, callback)
            return
        flags = mi.ParamFlags.Differentiable
        for f in field_names():
            callback.put(f, getattr(self.params, f), flags)

    def parameters_changed(self, keys=[]):
        """New parameters: the proxy quads and the BVH are rebuilt lazily, by
        :func:`ensure_proxies` before the next trace. Rasterised renders never trace, so an
        optimisation step of step 1 does not pay the BVH rebuild (a large share of an
        iteration)."""
        if self._building:
            _base(self).parameters_changed(self, keys)
            return
        if not keys or any(k in field_names() for k in keys):
            self._n = self._check_widths()
            self.version = getattr(self, "version", 0) + 1
            if not keys or any(k in GEOMETRY_FIELDS for k in keys):
                self._update_jitter()
                self.proxies_stale = True
                self.geometry_version = getattr(self, "geometry_version", 0) + 1

    def _update_jitter(self):
        with dr.suspend_grad():
            p = self.params
            ext = [float((dr.max(c) - dr.min(c))[0]) for c in (p.means.x, p.means.y, p.means.z)]
        diag = sum(e * e for e in ext) ** 0.5
        self.proxy_jitter = PROXY_JITTER * (diag if diag > 0 and diag == diag and diag < 1e30 else 1.0)

    # ------------------------------------------------------------- building
    def _check_widths(self):
        p = self.params
        n = dr.width(p.opacity_logit)
        for f in field_names():
            w = dr.width(getattr(p, f))
            if f == "sh":
                if n == 0 or w % (3 * n) != 0 or (w // (3 * n)) not in (1, 4, 9, 16):
                    raise ValueError(f"surfels: 'sh' has {w} values, not N*K*3 with N={n}, K in 1,4,9,16")
            elif w != n:
                raise ValueError(f"surfels: parameter '{f}' has {w} entries but 'opacity_logit' has {n}; "
                                 "assign all parameters with the same surfel count before update()")
        if n < 1:
            raise ValueError("surfels: at least one surfel is required")
        return n

    def _rebuild(self):
        """One gather kernel: parameters -> 4 corners per surfel, 2 faces per surfel."""
        n = self._check_widths()
        self._update_jitter()
        with dr.suspend_grad():
            p = self.params
            vertices, faces, bad = quad_buffers(p, self.proxy_jitter)
            self.nonfinite_count = int(dr.count(bad)[0]) if dr.width(bad) else 0
            if self.nonfinite_count:
                mi.Log(mi.LogLevel.Warn, f"surfels '{self.id()}': {self.nonfinite_count} surfel(s) "
                       "with NaN/Inf parameters are excluded from tracing")
            self._building = True
            try:
                mp = mi.traverse(self)
                mp["vertex_positions"] = dr.ravel(vertices)
                mp["faces"] = dr.ravel(faces)
                mp.update()
            finally:
                self._building = False
        self._n = n
        self.proxies_stale = False
        if not hasattr(self, "version"):
            self.version = 0          # bumped by parameter changes (not by lazy rebuilds)
            self.geometry_version = 0     # bumped by changes of GEOMETRY_FIELDS only

    def to_string(self):
        return f"SurfelShape[id={self.id()}, surfels={self.params.count}, sh_degree={self.params.sh_degree}]"


def ensure_proxies(scene, shapes) -> None:
    """Rebuild stale proxy quads of ``shapes`` and then the scene's BVH (before tracing)."""
    stale = [s for s in shapes if getattr(s, "proxies_stale", False)]
    for s in stale:
        s._rebuild()
    if stale:
        scene.parameters_changed()


def proxy_shift(index, jitter: float):
    """Offset of surfel ``index``'s proxy quad along its normal: jitter·(hash(i) − 0.5),
    a multiplicative integer hash in [0, 1) (shared by the tracer's quads and the rasteriser)."""
    hashed = mi.Float((index * 2654435761) >> 8) * (1.0 / (1 << 24))
    return jitter * (hashed - 0.5)


def quad_buffers(p: SurfelParams, jitter: float = 0.0):
    """Proxy geometry: ([4N] Point3f vertices, [2N] Vector3u faces, [N] Bool non-finite).

    Surfel i's quad is offset along its normal by jitter·(hash(i) − 0.5), with a
    multiplicative integer hash in [0, 1).
    Surfels whose peak opacity is below ALPHA_MIN, or with any non-finite
    parameter (geometry, colour or material), collapse to a zero-area quad and
    can never be hit, so they cannot put NaN into any buffer.
    """
    n = dr.width(p.opacity_logit)
    idx = dr.arange(mi.UInt32, 4 * n)
    s_idx, corner = idx // 4, idx % 4
    mean = dr.gather(mi.Point3f, p.means, s_idx)
    q = dr.gather(mi.Vector4f, p.quats, s_idx)
    ls = dr.gather(mi.Vector2f, p.log_scales, s_idx)
    op = K.opacity(dr.gather(mi.Float, p.opacity_logit, s_idx))
    t_u, t_v, nrm = K.quat_frame(q)
    s = K.scales(ls) * K.QUAD_SIGMA
    a = dr.select((corner == 1) | (corner == 2), 1.0, -1.0)
    b = dr.select(corner >= 2, 1.0, -1.0)
    shift = proxy_shift(s_idx, jitter)                                      # [4N]
    v = mean + t_u * (a * s.x) + t_v * (b * s.y) + nrm * shift
    finite = dr.all(dr.isfinite(v)) & dr.all(dr.isfinite(q)) & dr.isfinite(op) & _finite_rest(p, s_idx)
    keep = finite & (op >= K.ALPHA_MIN)
    v = dr.select(keep, v, dr.select(dr.all(dr.isfinite(mean)), mean, mi.Point3f(0.0)))
    f = dr.arange(mi.UInt32, 2 * n)
    quad, second = f // 2, (f % 2) == 1
    faces = mi.Vector3u(quad * 4, quad * 4 + dr.select(second, 2, 1), quad * 4 + dr.select(second, 3, 2))
    bad = ~dr.gather(mi.Bool, finite, dr.arange(mi.UInt32, n) * 4)
    return v, faces, bad


@functools.cache
def _make_class(variant: str):
    return variant_class("SurfelShape", SurfelShapeBase, mi.Mesh)


def shape_class():
    """The ``SurfelShape`` class of the active variant (mi.Mesh is per variant).

    Use ``isinstance(obj, SurfelShapeBase)`` to recognise surfels in any variant.
    """
    return _make_class(mi.variant())


def _finite_rest(p: SurfelParams, s_idx):
    """[4N] Bool: colour and material parameters of the surfel are finite."""
    ok = dr.all(dr.isfinite(dr.gather(mi.Color3f, p.albedo, s_idx)))
    ok &= dr.isfinite(dr.gather(mi.Float, p.roughness, s_idx) + dr.gather(mi.Float, p.metallic, s_idx))
    kc = p.sh_coeffs
    for k in range(kc):
        ok &= dr.all(dr.isfinite(dr.gather(mi.Color3f, p.sh, s_idx * kc + k)))
    return ok


def register():
    mi.register_shape("surfels", lambda props: shape_class()(props))


def _base(obj):
    return type(obj).__bases__[0]
