"""Coverage masks for panorama completion (Appendix "Training Dataset").

``mask_bank``: alpha and normals traced (:mod:`comgs_dr.surfels.panorama`) from random points
in procedural surfel scenes (``from_mesh``: outdoor yards and rooms with missing
walls/ceilings), with the object's footprint excluded and surfels inside a random cone
(biased upwards) dropped, so masks have surfel edges and open upper hemispheres.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np
import trimesh
from tqdm import tqdm

from comgs_dr.surfels.from_mesh import from_mesh
from comgs_dr.surfels.panorama import PanoramaConfig, trace_panorama
from comgs_dr.surfels.scene import gbuffer_scene


@dataclass
class MaskSample:
    alpha: np.ndarray      # [H, W] coverage in [0, 1]
    normal: np.ndarray     # [H, W, 3] unit normals where covered, 0 elsewhere
    coverage: float        # solid-angle-weighted mean of alpha

    def as_dict(self) -> dict:
        return {"alpha": self.alpha, "normal": self.normal, "coverage": self.coverage}


def _box_room(rng, size, open_top: bool):
    sx, sy, sz = size
    parts = [trimesh.creation.box((sx, sy, 0.05), transform=_tr([0, 0, -0.025]))]
    if not open_top:
        parts.append(trimesh.creation.box((sx, sy, 0.05), transform=_tr([0, 0, sz + 0.025])))
    for sgn in (-1, 1):
        if rng.random() < 0.8:
            parts.append(trimesh.creation.box((0.05, sy, sz), transform=_tr([sgn * sx / 2, 0, sz / 2])))
        if rng.random() < 0.8:
            parts.append(trimesh.creation.box((sx, 0.05, sz), transform=_tr([0, sgn * sy / 2, sz / 2])))
    return parts


def _tr(t):
    return trimesh.transformations.translation_matrix(t)


def _furniture(rng, extent, n):
    parts = []
    for _ in range(n):
        x, y = rng.uniform(-extent / 2, extent / 2, 2)
        k = rng.integers(3)
        if k == 0:
            s = rng.uniform(0.2, 1.2, 3)
            parts.append(trimesh.creation.box(s, transform=_tr([x, y, s[2] / 2])))
        elif k == 1:
            r = rng.uniform(0.1, 0.5)
            m = trimesh.creation.icosphere(subdivisions=2, radius=r)
            m.apply_translation([x, y, r])
            parts.append(m)
        else:
            r, hh = rng.uniform(0.05, 0.3), rng.uniform(0.5, 3.0)
            parts.append(trimesh.creation.cylinder(radius=r, height=hh, transform=_tr([x, y, hh / 2])))
    return parts


def random_surfel_scene(rng, n_surfels: int):
    """(surfel params, sampling box for the trace point) of a procedural indoor/outdoor scene."""
    if rng.random() < 0.5:      # outdoor yard: ground + objects, open sky
        ext = rng.uniform(6, 14)
        parts = [trimesh.creation.box((ext, ext, 0.05), transform=_tr([0, 0, -0.025]))]
        parts += _furniture(rng, ext, int(rng.integers(4, 14)))
        box = (np.array([-1.0, -1.0, 0.2]), np.array([1.0, 1.0, 1.2]))
    else:                       # room, some walls or the ceiling possibly missing
        size = np.array([rng.uniform(3, 8), rng.uniform(3, 8), rng.uniform(2.2, 3.5)])
        parts = _box_room(rng, size, open_top=rng.random() < 0.3)
        parts += _furniture(rng, min(size[:2]) * 0.9, int(rng.integers(2, 8)))
        box = (np.array([-size[0] / 4, -size[1] / 4, 0.3]),
               np.array([size[0] / 4, size[1] / 4, size[2] * 0.6]))
    mesh = trimesh.util.concatenate(parts)
    mesh.visual.vertex_colors = np.tile([128, 128, 128, 255], (len(mesh.vertices), 1)).astype(np.uint8)
    params = from_mesh(mesh, n_surfels, seed=int(rng.integers(1 << 30)), opacity=0.95)
    return params, box


def _random_cone(rng):
    """Unit axis (biased upwards) and half-angle of a random-region dropout."""
    z = rng.uniform(-0.3, 1.0) if rng.random() < 0.7 else rng.uniform(-1.0, 1.0)
    phi = rng.uniform(0, 2 * np.pi)
    r = np.sqrt(max(0.0, 1 - z * z))
    return np.array([r * np.cos(phi), r * np.sin(phi), z]), np.radians(rng.uniform(15, 70))


def mask_bank(n: int, h: int = 64, w: int = 128, seed: int = 0, n_surfels: int = 20000,
              points_per_scene: int = 8, dropout: float = 0.7, progress: bool = False
              ) -> list[dict]:
    """``n`` masks [{alpha [h, w], normal [h, w, 3], coverage}] traced from random points of
    random procedural surfel scenes; with probability ``dropout`` the surfels inside a random
    cone seen from the point are dropped first (Appendix, "random-region dropout")."""

    rng = np.random.default_rng(seed)
    out: list[dict] = []
    cfg = PanoramaConfig(width=w, height=h, max_hits=16, exclude_radius=0.15)
    it = range(-(-n // points_per_scene))
    if progress:
        it = tqdm(it, desc="masks", unit="scene")
    for _ in it:
        params, (lo, hi) = random_surfel_scene(rng, n_surfels)
        means = np.asarray(dr.detach(params.means), np.float64).T                     # [N, 3]
        full = gbuffer_scene(params, [], targets="weight")
        for _ in range(points_per_scene):
            if len(out) >= n:
                break
            p = rng.uniform(lo, hi)
            scene = full
            if rng.random() < dropout:
                axis, ang = _random_cone(rng)
                v = means - p
                cosang = (v @ axis) / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
                keep = cosang < np.cos(ang)
                if keep.sum() > 100:
                    scene = gbuffer_scene(params.subset(keep), [], targets="weight")
            pano = trace_panorama(scene, p, cfg)
            out.append(MaskSample(pano["alpha"], pano["normal"], float(pano["meta"]["coverage"])).as_dict())
    return out
