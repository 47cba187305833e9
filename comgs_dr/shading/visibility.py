"""Visibility sources for deferred shading, and their one factory.

A source maps (shading-point index [M], world direction [M]) to (occlusion O [M], indirect
radiance L_in [M]) for the paper's L_i(ω) = (1 − O(ω))·L_dir(ω) + L_in(ω):

* :class:`SopVisibility` — KNN interpolation of the Surface Octahedral Probes' textures
  (computed once per set of points, eq. knn), differentiable w.r.t. the probe atlas;
* :class:`TraceVisibility` — per-call ray tracing through the surfels (IRGS-style
  baseline), detached and evaluated before shading;
* :class:`NoVisibility` — O = 0, L_in = 0 (convex objects, or to isolate direct light).

:func:`make_visibility` builds any of them; trace rays start ``TRACE_OFFSET_FRAC`` × the
object size (:func:`comgs_dr.surfels.params.object_size`) along the normal unless an
absolute offset is given.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from comgs_dr.core import octahedral as octa
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.sops.query import ProbeGrid, query
from comgs_dr.surfels.params import object_size
from comgs_dr.surfels.trace import trace_visibility

KINDS = ("sops", "trace", "none")
TRACE_OFFSET_FRAC = 0.01      # trace-ray origin offset along the normal, × object size


class NoVisibility:
    name = "none"

    def prepare(self, pts):
        pass

    def lookup(self, pid, wi, need_radiance: bool):
        return mi.Float(0.0), (mi.Color3f(0.0) if need_radiance else None)


class SopVisibility:
    """Surface Octahedral Probes: ``atlas`` is the flat bordered 4-channel atlas (the
    optimised parameter), ``grid`` a ``sops.query.ProbeGrid`` over the probe positions."""
    name = "sops"

    def __init__(self, atlas, grid, res: int, k: int = 8, filter: str = "bilinear"):
        if filter not in ("bilinear", "nearest"):
            raise ValueError(f"SopVisibility: filter must be 'bilinear' or 'nearest', got {filter!r}")
        self.atlas, self.grid, self.res, self.k, self.filter = atlas, grid, res, k, filter
        self.knn, self._knn_key = None, None

    def prepare(self, pts):
        """KNN weights of the points (reused while the same position variables come back:
        fixed geometry is queried once per view)."""
        key = tuple(c.index for c in (pts.position.x, pts.position.y, pts.position.z))
        if key == self._knn_key and all(key):
            return
        with dr.suspend_grad():
            self.knn = query(self.grid, dr.detach(pts.position), dr.detach(pts.normal), self.k)
            dr.eval(self.knn.index, self.knn.weight)
        self._knn_key = key
        # hold the keyed variables: a freed variable's index is reused by new arrays, and a
        # stale key would then serve another point set's (differently sized) neighbours
        self._knn_pos = pts.position

    def lookup(self, pid, wi, need_radiance: bool):
        if self.knn is None:
            raise RuntimeError("SopVisibility.lookup before prepare()")
        taps_fn = octa.bilinear_taps if self.filter == "bilinear" else octa.nearest_taps
        taps = taps_fn(mi.UInt32(0), octa.dir_to_uv(wi), self.res)               # tile 0
        tile = (self.res + 2) ** 2
        acc = mi.Vector4f(0.0)
        for j in range(self.k):
            slot = pid * self.k + j
            probe = dr.gather(mi.UInt32, self.knn.index, slot)
            w = dr.gather(mi.Float, self.knn.weight, slot)
            shifted = octa.Taps([i + probe * tile for i in taps.index], taps.weight)
            acc += w * octa.lookup(self.atlas, shifted, 4)
        occ = dr.clip(acc.w, 0.0, 1.0)
        rad = mi.Color3f(dr.maximum(acc.x, 0), dr.maximum(acc.y, 0), dr.maximum(acc.z, 0))
        return occ, (rad if need_radiance else None)


class TraceVisibility:
    """Per-direction ray tracing through the surfels of ``scene`` (origins offset by
    ``offset`` along the normal: alpha-blended depth lies inside near-opaque surfaces)."""
    name = "trace"

    def __init__(self, scene, offset: float, max_hits: int = 8, colour_space: str = "srgb"):
        self.scene, self.offset, self.max_hits = scene, float(offset), max_hits
        self.colour_space = colour_space
        self.pts = None

    def prepare(self, pts):
        self.pts = pts

    def lookup(self, pid, wi, need_radiance: bool):
        with dr.suspend_grad():
            x = dr.gather(mi.Point3f, mi.Point3f(dr.detach(self.pts.position)), pid)
            n = dr.gather(mi.Vector3f, mi.Vector3f(dr.detach(self.pts.normal)), pid)
            occ, rad = trace_visibility(self.scene, x + n * self.offset, dr.detach(wi),
                                        self.max_hits, radiance=need_radiance,
                                        colour_space=self.colour_space)
        return occ, rad


def make_visibility(kind: str, *, scene=None, probes: ProbeSet | str | None = None, k: int = 8,
                    trace_hits: int = 8, trace_offset: float | None = None,
                    offset_frac: float = TRACE_OFFSET_FRAC):
    """The visibility source ``kind`` ('sops', 'trace' or 'none').

    'sops' needs ``probes`` (a ProbeSet or a probe file) and interpolates ``k`` neighbours;
    'trace' needs ``scene`` (surfels only) and starts its rays ``trace_offset`` (scene units)
    along the normal, default ``offset_frac`` × the object size of the scene's surfels.
    """
    if kind not in KINDS:
        raise ValueError(f"visibility must be one of {', '.join(KINDS)}, got {kind!r}")
    if kind == "none":
        return NoVisibility()
    if kind == "trace":
        if scene is None:
            raise ValueError("visibility 'trace' needs the surfel scene")
        if trace_offset is None or trace_offset <= 0:
            sizes = [object_size(s.params) for s in scene.shapes() if hasattr(s, "params")]
            if not sizes:
                raise ValueError("visibility 'trace': the scene has no surfels shape to trace")
            trace_offset = offset_frac * max(sizes)
        return TraceVisibility(scene, trace_offset, trace_hits)
    if probes is None:
        raise ValueError("visibility 'sops' needs probes (a ProbeSet or a probes.npz file)")
    if not isinstance(probes, ProbeSet):
        probes = ProbeSet.load(probes)
    return SopVisibility(probes.atlas(), ProbeGrid(probes.positions, probes.radius), probes.res, k)
