"""The ``surfels`` shape plugin: 2D Gaussian surfels as a Mitsuba triangle mesh.

Each surfel is traced as one quad (2 triangles) spanning ±3σ in its tangent
plane; ``surfel = prim_index // 2``. The quad is only the ray-tracing proxy:
integrators recompute t, (u, v) and α analytically from the parameters (see
:mod:`comgs_dr.surfels.kernel`), which is what makes them differentiable.
"""
from __future__ import annotations

import dataclasses
import os

import drjit as dr
import mitsuba as mi

from . import kernel as K
from .params import SurfelParams, field_names


class SurfelShape(mi.Mesh):
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
       - Not supported (surfels are stored in world space); refused if given.

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
        if props.has_property("to_world"):
            raise ValueError("surfels: 'to_world' is not supported; transform the PLY "
                             "(comgs_dr.surfels.io) before loading")
        if params is None:
            if not props.has_property("filename"):
                raise ValueError("surfels: give <string name=\"filename\"> (a surfel PLY) "
                                 "or construct SurfelShape(props, params=...) from Python")
            fname = str(props["filename"])
            resolved = str(mi.file_resolver().resolve(fname))
            if not os.path.exists(resolved):
                raise FileNotFoundError(f"surfels: filename '{fname}' not found")
            from .io import load_ply
            params = load_ply(resolved)
        n = params.count
        if n < 1:
            raise ValueError("surfels: at least one surfel is required")
        super().__init__("surfels", 4 * n, 2 * n, props)
        self.params = params
        self._building = False
        self.nonfinite_count = 0
        self._rebuild()

    # ------------------------------------------------------------ interface
    @staticmethod
    def from_params(params: SurfelParams, id: str = "surfels") -> "SurfelShape":
        props = mi.Properties("surfels")
        props.set_id(id)
        return SurfelShape(props, params=params)

    def set_params(self, params: SurfelParams) -> None:
        """Replace all surfels (any count) and rebuild quads/BVH via the parent scene update."""
        for f in field_names():
            setattr(self.params, f, getattr(params, f))
        self._rebuild()

    def surfel_count(self) -> int:
        return self.params.count

    # -------------------------------------------------------- Mitsuba hooks
    def traverse(self, callback):
        if self._building:   # internal: expose the mesh buffers to rewrite them
            super().traverse(callback)
            return
        flags = mi.ParamFlags.Differentiable
        for f in field_names():
            callback.put(f, getattr(self.params, f), flags)

    def parameters_changed(self, keys=[]):
        if self._building:
            super().parameters_changed(keys)
            return
        if not keys or any(k in field_names() for k in keys):
            self._rebuild()
        super().parameters_changed(keys)

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
        with dr.suspend_grad():
            p = self.params
            vertices, faces, bad = quad_buffers(p)
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

    def to_string(self):
        return f"SurfelShape[id={self.id()}, surfels={self.params.count}, sh_degree={self.params.sh_degree}]"


def quad_buffers(p: SurfelParams):
    """Proxy geometry: ([4N] Point3f vertices, [2N] Vector3u faces, [N] Bool non-finite).

    Surfels whose peak opacity is below ALPHA_MIN, or whose parameters are not
    finite, collapse to a zero-area quad and can never be hit.
    """
    n = dr.width(p.opacity_logit)
    idx = dr.arange(mi.UInt32, 4 * n)
    s_idx, corner = idx // 4, idx % 4
    mean = dr.gather(mi.Point3f, p.means, s_idx)
    q = dr.gather(mi.Vector4f, p.quats, s_idx)
    ls = dr.gather(mi.Vector2f, p.log_scales, s_idx)
    op = K.opacity(dr.gather(mi.Float, p.opacity_logit, s_idx))
    t_u, t_v, _ = K.quat_frame(q)
    s = K.scales(ls) * K.QUAD_SIGMA
    a = dr.select((corner == 1) | (corner == 2), 1.0, -1.0)
    b = dr.select(corner >= 2, 1.0, -1.0)
    v = mean + t_u * (a * s.x) + t_v * (b * s.y)
    finite = dr.all(dr.isfinite(v)) & dr.all(dr.isfinite(q)) & dr.isfinite(op)
    keep = finite & (op >= K.ALPHA_MIN)
    v = dr.select(keep, v, dr.select(dr.all(dr.isfinite(mean)), mean, mi.Point3f(0.0)))
    f = dr.arange(mi.UInt32, 2 * n)
    quad, second = f // 2, (f % 2) == 1
    faces = mi.Vector3u(quad * 4, quad * 4 + dr.select(second, 2, 1), quad * 4 + dr.select(second, 3, 2))
    bad = ~dr.gather(mi.Bool, finite, dr.arange(mi.UInt32, n) * 4)
    return v, faces, bad


def register():
    mi.register_shape("surfels", lambda props: SurfelShape(props))
