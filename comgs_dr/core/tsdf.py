"""TSDF fusion of depth maps into a voxel grid and its zero level set (2DGS's mesh extraction).

Each view (OpenCV intrinsics ``K`` and world-to-camera ``w2c``, z-depth map, coverage mask)
updates the voxels it sees within the band |z_pixel − z_voxel| ≤ trunc with the truncated
signed distance along the optical axis ``s = (z_pixel − z_voxel) / trunc``, averaged over
views with weight 1 (as Open3D's ``ScalableTSDFVolume``, which 2DGS uses; Open3D is not a
dependency, and the update is a few vectorised lines). Outside the band a view only votes:

* *carved* — its pixel has no surface (coverage < 0.5, the capture's background): space
  carving, strong evidence that the voxel is outside;
* *front* — it lies more than ``trunc`` in front of the surface (weak: a pixel whose
  depth mixes a surface with what shows through a hole in it lies too far);
* *behind* — more than ``trunc`` behind the surface.

A voxel with band observations takes the mean of its band values and its carved and front
votes (+1, as a standard TSDF integrates far-front voxels). A voxel with none is outside
(+1) if any view carved it, else inside (−1) when its behind votes outnumber its front
votes; a voxel with band observations but no carving is also inside when its behind votes
outnumber its band and front observations together (one view that sees through a hole
cannot open the inside) — unless its connected region of such voxels reaches the grid's
border (space no view saw, e.g. beyond the frames' edges or under an object on a table),
which is outside. With noisy surfel depths, letting one front vote decide carves bubbles
inside the object, and a plain majority over all votes fills the unseen space under an
object captured from above.

The zero level set is extracted by ``skimage.measure.marching_cubes`` on the grid padded
with +1, so the surface is closed. Colours (any [H, W, C] image per view) are averaged over
the voxels within the band and interpolated trilinearly at the vertices.
"""
from __future__ import annotations

import numpy as np


class TSDFVolume:
    """A dense grid over ``bounds`` ([2, 3] lo/hi) with ``resolution`` voxels along the
    longest side; ``trunc`` is the truncation distance in voxels."""

    def __init__(self, bounds, resolution: int, trunc_voxels: float = 4.0, channels: int = 3):
        lo, hi = (np.asarray(b, np.float64) for b in np.asarray(bounds, np.float64))
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
            raise ValueError(f"TSDFVolume: bounds must be finite with hi > lo, got {lo}, {hi}")
        if not 8 <= int(resolution) <= 1024:
            raise ValueError(f"TSDFVolume: resolution must be in [8, 1024], got {resolution}")
        self.voxel = float((hi - lo).max()) / int(resolution)
        self.dims = tuple(int(np.ceil(e / self.voxel)) + 1 for e in hi - lo)    # (X, Y, Z)
        self.lo = lo
        self.trunc = float(trunc_voxels) * self.voxel
        n = int(np.prod(self.dims))
        self.tsdf = np.zeros(n, np.float32)            # Σ s over band observations
        self.weight = np.zeros(n, np.float32)          # number of band observations
        self.carved = np.zeros(n, np.uint16)           # background-pixel votes
        self.front = np.zeros(n, np.uint16)            # far-in-front votes
        self.behind = np.zeros(n, np.uint16)           # behind-a-surface votes
        self.color = np.zeros((n, channels), np.float32)
        self.color_w = np.zeros(n, np.float32)

    def _points(self, sl: slice) -> np.ndarray:
        i = np.arange(sl.start, sl.stop)
        X, Y, Z = self.dims
        ijk = np.stack([i // (Y * Z), (i // Z) % Y, i % Z], -1)
        return (self.lo + ijk * self.voxel).astype(np.float32)              # [n, 3]

    def integrate(self, depth_z, covered, K, w2c, color=None, known=None,
                  chunk: int = 1 << 21) -> None:
        """Fuse one view: ``depth_z`` [H, W] z-depth, ``covered`` [H, W] bool, ``K`` [3, 3],
        ``w2c`` [4, 4] (OpenCV: +X right, +Y down, +Z forward), ``color`` [H, W, C] or None;
        pixels where ``known`` [H, W] is False (untrusted depth) are skipped."""
        H, W = depth_z.shape
        K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
        R, t = w2c[:3, :3].astype(np.float32), w2c[:3, 3].astype(np.float32)
        ok_px = covered & np.isfinite(depth_z) & (depth_z > 0)
        n = self.tsdf.size
        for s in range(0, n, chunk):
            sl = slice(s, min(n, s + chunk))
            pc = self._points(sl) @ R.T + t                                 # [n, 3]
            z = pc[:, 2]
            zs = np.where(z > 1e-6, z, 1.0)
            u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
            v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
            seen = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            idx = np.flatnonzero(seen)
            px = v[idx].astype(np.int64) * W + u[idx].astype(np.int64)
            if known is not None:
                trusted = known.ravel()[px]
                idx, px = idx[trusted], px[trusted]
            hit = ok_px.ravel()[px]
            sdf = depth_z.ravel()[px] - z[idx]
            band = hit & (np.abs(sdf) <= self.trunc)
            g = sl.start + idx
            gb = g[band]
            self.tsdf[gb] += sdf[band] / self.trunc
            self.weight[gb] += 1.0
            for votes, which in ((self.carved, ~hit), (self.front, hit & (sdf > self.trunc)),
                                 (self.behind, hit & (sdf < -self.trunc))):
                gv = g[which]
                votes[gv] = np.minimum(votes[gv], 65534) + 1
            if color is not None:
                self.color[gb] += color.reshape(H * W, -1)[px[band]]
                self.color_w[gb] += 1.0

    def field(self) -> np.ndarray:
        """The signed field [X, Y, Z] (see the module docstring)."""
        from scipy.ndimage import label   # only when a field is built
        free = self.carved.astype(np.float32) + self.front
        inside = ((self.carved == 0) & (self.behind > self.front + self.weight))
        inside = inside.reshape(self.dims)
        lab, _ = label(inside)
        edge = np.unique(np.concatenate([lab[0].ravel(), lab[-1].ravel(), lab[:, 0].ravel(),
                                         lab[:, -1].ravel(), lab[:, :, 0].ravel(),
                                         lab[:, :, -1].ravel()]))
        inside &= ~np.isin(lab, edge[edge > 0])          # unseen space open to the border
        f = np.where(self.weight > 0, (self.tsdf + free) / np.maximum(self.weight + free, 1.0),
                     1.0).reshape(self.dims)
        return np.where(inside, -1.0, f).astype(np.float32)

    def extract(self):
        """(vertices [V, 3] world, faces [F, 3], colours [V, C] or None) of the zero level set;
        ValueError if the field has no surface."""
        from skimage.measure import marching_cubes   # heavy: only when a mesh is extracted
        f = np.pad(self.field(), 1, constant_values=1.0)
        if f.min() >= 0 or f.max() <= 0:
            raise ValueError("TSDF: no surface in the volume (every voxel is on one side); "
                             "check the bounds and that the views see the surfels")
        verts, faces, _, _ = marching_cubes(f, level=0.0, allow_degenerate=False)
        colors = None
        if self.color_w.any():
            from scipy.ndimage import map_coordinates
            c = np.pad(self.color.reshape(*self.dims, -1), ((1, 1),) * 3 + ((0, 0),))
            w = np.pad(self.color_w.reshape(self.dims), 1)
            cw = map_coordinates(w, verts.T, order=1)
            colors = np.stack([map_coordinates(c[..., k], verts.T, order=1)
                               for k in range(c.shape[-1])], -1) / np.maximum(cw, 1e-6)[:, None]
            bare = cw < 1e-3                  # no coloured voxel around: the nearest coloured
            if bare.any() and (~bare).any():  # vertex's colour
                from scipy.spatial import cKDTree
                colors[bare] = colors[~bare][cKDTree(verts[~bare]).query(verts[bare])[1]]
        world = self.lo + (verts - 1.0) * self.voxel
        return world, faces.astype(np.int64), colors
