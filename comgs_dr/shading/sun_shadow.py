"""A sun's shadow map: the placed objects' transmittance toward the sun, traced once.

Why: a compact source's shadow needs its visibility at a finer angle than the occlusion
probes' texels (4–11°), and tracing sun rays per pixel and frame (exact) costs more than the
rest of a frame: a ray that crosses the object composites many semi-transparent surfels. The sun's direction is fixed for a composition, so its visibility is a 2D function
of where a receiver's ray crosses the objects: the classic shadow map, stored as
transmittance (soft, deep: every surfel composited) rather than as a first depth.

Build: an orthographic grid of ``res``² rays over the objects' bounding sphere (radius R,
centre c), starting on the plane through c + 1.5 R d and travelling along −d (d: the sun's
unit world direction); per texel the transmittance T and the opacity-weighted depth t̄ of
its surfels (distance from the plane, ``surfels.trace`` semantics: every surfel composited
up to T < 1e-4).

Lookup (a :mod:`comgs_dr.shading.visibility` source, occlusion only): a receiver x lies at
depth s = 1.5 R − (x − c)·d. Its ray toward ω (a direction inside the sun's disk) reaches the
objects' mid-depth 1.5 R after τ = (s − 1.5 R) / (ω·d), at the lateral position
p⊥(x) + τ p⊥(ω); the occlusion there is the bilinear blend of the four texels' 1 − T, each
counted only if the receiver lies behind that texel's occluders (s > t̄: a surface between
the sun and the objects stays lit). Sampling ω over the sun's texels (the map split by
:func:`comgs_dr.shading.sun.split_sun`) gives the penumbra of the sun's estimated size; the
mid-depth crossing is exact for ω = d and off by (t̄ − 1.5 R)·tan∠(ω, d) elsewhere (< 0.03 R
for a sun of 2° radius).
"""
from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels import composite

LEAD = 1.5          # the grid's plane lies LEAD × R from the centre, toward the sun


def _basis(d: np.ndarray):
    """Two unit vectors orthogonal to unit ``d`` and to each other."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


class SunShadowMap:
    """Occlusion toward a sun by the surfels of ``scene`` (a scene of surfels shapes only),
    cached in a ``res``² map over the sphere (``centre`` [3], ``radius``) that holds them.

    ``direction`` [3]: unit world direction toward the sun. Build cost: ``res``² traced
    rays, once (``build_seconds``). ``max_hits``: K per tracing pass (all passes run)."""
    name = "sun_map"

    def __init__(self, scene, direction, centre, radius: float, res: int = 512,
                 max_hits: int = 16):
        if res < 2:
            raise ValueError(f"SunShadowMap: res must be ≥ 2, got {res}")
        d = np.asarray(direction, np.float64)
        if d.shape != (3,) or not np.isfinite(d).all() or np.linalg.norm(d) < 1e-9:
            raise ValueError(f"SunShadowMap: direction must be a finite non-zero 3-vector, "
                             f"got {direction!r}")
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"SunShadowMap: radius must be > 0, got {radius!r}")
        self.d = d / np.linalg.norm(d)
        self.e1, self.e2 = _basis(self.d)
        self.c, self.R, self.res = np.asarray(centre, np.float64), float(radius), int(res)
        self.T, self.depth = self._trace(scene, max_hits)
        self.pts = None

    def _trace(self, scene, max_hits):
        """(T [res²], t̄ [res²]) as flat jit arrays, row-major (v rows, u columns)."""
        t0 = time.perf_counter()
        res, R = self.res, self.R
        g = (np.arange(res) + 0.5) / res * 2.0 - 1.0
        v, u = np.meshgrid(g * R, g * R, indexing="ij")
        org = (self.c + LEAD * R * self.d)[None] + u.reshape(-1, 1) * self.e1 \
            + v.reshape(-1, 1) * self.e2
        shapes = composite.surfel_shapes(scene, "SunShadowMap")
        eps = composite.auto_epsilon(scene, shapes)
        with dr.suspend_grad():
            ray = mi.Ray3f(to_jit(mi.Point3f, org.astype(np.float32).T),
                           mi.Vector3f(*map(float, -self.d)))
            _, out, _, _ = composite.trace_composite(scene, shapes, ray, max_hits, eps,
                                                     ("weight", "depth_unbiased"), max_passes=64,
                                                     keep_hits=False)
            W = dr.clip(out["weight"], 0.0, 1.0)
            depth = dr.select(W > 1e-6, out["depth_unbiased"], np.inf)
            T = 1.0 - W
            dr.eval(T, depth)
        self.build_seconds = time.perf_counter() - t0
        return mi.Float(T), mi.Float(depth)

    def coverage(self) -> float:
        """Fraction of the map's texels with occlusion > 1e-3 (a build check)."""
        return float(np.mean(np.asarray(self.T) < 1.0 - 1e-3))

    def prepare(self, pts):
        self.pts = pts

    def occlusion(self, x, w):
        """O [N] toward unit directions ``w`` [N] from points ``x`` [N] (world)."""
        c, d = mi.Point3f(*map(float, self.c)), mi.Vector3f(*map(float, self.d))
        e1, e2 = mi.Vector3f(*map(float, self.e1)), mi.Vector3f(*map(float, self.e2))
        rel = x - c
        s = LEAD * self.R - dr.dot(rel, d)
        wd = dr.dot(w, d)
        tau = (s - LEAD * self.R) / dr.maximum(wd, 1e-3)
        pu, pv = dr.dot(rel, e1) + tau * dr.dot(w, e1), dr.dot(rel, e2) + tau * dr.dot(w, e2)
        res = self.res
        fu = (pu / self.R + 1.0) * 0.5 * res - 0.5
        fv = (pv / self.R + 1.0) * 0.5 * res - 0.5
        u0, v0 = dr.floor(fu), dr.floor(fv)
        au, av = fu - u0, fv - v0
        occ = mi.Float(0.0)
        for du, dv, wt in ((0, 0, (1 - au) * (1 - av)), (1, 0, au * (1 - av)),
                           (0, 1, (1 - au) * av), (1, 1, au * av)):
            iu, iv = mi.Int32(u0) + du, mi.Int32(v0) + dv
            inside = (iu >= 0) & (iu < res) & (iv >= 0) & (iv < res) & (wd > 0.0)
            idx = mi.UInt32(dr.select(inside, iv * res + iu, 0))
            T = dr.gather(mi.Float, self.T, idx, inside)
            t_bar = dr.gather(mi.Float, self.depth, idx, inside)
            behind = inside & (s > t_bar)
            occ += dr.select(behind, wt * (1.0 - T), 0.0)
        return dr.clip(occ, 0.0, 1.0)

    def lookup(self, pid, wi, need_radiance: bool):
        if self.pts is None:
            raise RuntimeError("SunShadowMap.lookup before prepare()")
        x = dr.gather(mi.Point3f, mi.Point3f(dr.detach(self.pts.position)), pid)
        return self.occlusion(x, dr.detach(wi)), (mi.Color3f(0.0) if need_radiance else None)
