"""The detail stress object: fine texture and thin structures for step-1 tests.

Real NeRF-synthetic objects (ficus leaves, lego studs, ship rigging) have what smooth,
textured meshes lack: structures thinner than a pixel at 1/8 resolution and albedo with
detail at every scale. This object has both, built from real imagery (scikit-image's
bundled photographs, no download):

* a sphere (radius 0.5) wrapped in the ``astronaut`` photograph (lat-long UVs);
* a cage of 16 vertical rods at radius 0.85 whose radii run from 0.004 to 0.04 (at the
  default 100 px, fov 40° and camera distance ~3.2, one pixel is ~0.023: sub-pixel to
  ~3 px wide), textured with stripes of the ``coffee`` photograph;
* two thin rings (tube radius 0.012) joining the rods at the top and bottom, 8 diagonal
  spokes (radius 0.008) from the rings to the sphere, and a thin disc (a "leaf",
  thickness 0.01) cut by slots, seen edge-on from the equator.

Written as OBJ (+ MTL + PNG atlas: astronaut left, coffee right), y up, so that
``make_object_dataset`` scales and shades it like any mesh.

The parametric surfaces are built here rather than with ``trimesh.creation`` because those
primitives carry no texture coordinates (and weld the UV seam), and the OBJ is written with
trimesh's exporter.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

N_RODS = 16


def _grid(fn, nu: int, nv: int, u_range=(0.0, 1.0), v_range=(0.0, 1.0), uv_box=(0, 0, 1, 1)):
    """Vertices [(nu+1)(nv+1), 3], UVs and faces of a parametric patch ``fn(u, v)``.

    The seam column is duplicated so that UVs do not wrap; ``uv_box`` (u0, v0, u1, v1)
    places the patch in the texture atlas.
    """
    u = np.linspace(*u_range, nu + 1)
    v = np.linspace(*v_range, nv + 1)
    U, V = np.meshgrid(u, v, indexing="ij")                      # [nu+1, nv+1]
    P = fn(U, V).reshape(-1, 3)                                  # [(nu+1)(nv+1), 3]
    su = (U - u_range[0]) / (u_range[1] - u_range[0])
    sv = (V - v_range[0]) / (v_range[1] - v_range[0])
    uv = np.stack([uv_box[0] + su * (uv_box[2] - uv_box[0]),
                   uv_box[1] + sv * (uv_box[3] - uv_box[1])], -1).reshape(-1, 2)
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    return P, uv, faces


def _tube(p0, p1, radius, n_around=8, n_along=4, uv_box=(0.5, 0, 1, 1)):
    """Capped cylinder from ``p0`` to ``p1`` (caps are fans with a degenerate centre row)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    t = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0, 0]) if abs(t[0]) < 0.9 else np.array([0, 0, 1.0])
    e1 = np.cross(t, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(t, e1)

    def ring(ang):
        return np.cos(ang)[..., None] * e1 + np.sin(ang)[..., None] * e2

    def side(U, V):
        return p0 + V[..., None] * axis + radius * ring(2 * np.pi * U)

    def cap(end):
        return lambda U, V: end + radius * V[..., None] * ring(2 * np.pi * U)
    return _merge([_grid(side, n_around, n_along, uv_box=uv_box),
                   _grid(cap(p0), n_around, 1, uv_box=uv_box),
                   _grid(cap(p1), n_around, 1, uv_box=uv_box)])


def _merge(parts):
    """Concatenate (vertices, uvs, faces) parts into one."""
    verts, uvs, faces, off = [], [], [], 0
    for v, uv, f in parts:
        verts.append(v)
        uvs.append(uv)
        faces.append(f + off)
        off += len(v)
    return np.concatenate(verts), np.concatenate(uvs), np.concatenate(faces)


def detail_parts() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The object's parts as (vertices, uvs, faces), y up, within [-1, 1]^3."""
    parts = []

    def sphere(U, V):                                            # U: azimuth, V: polar
        th, ph = np.pi * V, 2 * np.pi * U
        return 0.5 * np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1)
    parts.append(_grid(sphere, 96, 48, uv_box=(0.0, 1.0, 0.5, 0.0)))
    radii = np.geomspace(0.004, 0.04, N_RODS)
    for i, r in enumerate(radii):
        a = 2 * np.pi * i / N_RODS
        x, z = 0.85 * np.cos(a), 0.85 * np.sin(a)
        box = (0.5 + 0.5 * i / N_RODS, 0.0, 0.5 + 0.5 * (i + 1) / N_RODS, 1.0)
        parts.append(_tube((x, -0.8, z), (x, 0.8, z), r, n_around=8, n_along=8, uv_box=box))
    for y, box in ((0.8, (0.5, 0.0, 1.0, 0.05)), (-0.8, (0.5, 0.95, 1.0, 1.0))):
        def ring(U, V, y=y):
            ph, th = 2 * np.pi * U, 2 * np.pi * V
            R = 0.85 + 0.012 * np.cos(th)
            return np.stack([R * np.cos(ph), y + 0.012 * np.sin(th), R * np.sin(ph)], -1)
        parts.append(_grid(ring, 128, 6, uv_box=box))
    for i in range(8):
        a = 2 * np.pi * (i + 0.5) / 8
        y = 0.8 if i % 2 == 0 else -0.8
        outer = (0.85 * np.cos(a), y, 0.85 * np.sin(a))
        inner = (0.3 * np.cos(a), 0.35 * np.sign(y), 0.3 * np.sin(a))   # inside the sphere
        parts.append(_tube(outer, inner, 0.008, n_around=6, n_along=4,
                           uv_box=(0.5, 0.4 + 0.02 * i, 1.0, 0.42 + 0.02 * i)))
    parts.extend(_slotted_leaf())
    return parts


def _slotted_leaf():
    """A thin disc in the y = -0.62 plane (radius 0.8, thickness 0.01) with 6 radial slots:
    two faces plus a rim, as quads between slot boundaries."""
    out = []
    n_slots, slot_frac = 6, 0.35
    for k in range(n_slots):
        a0 = 2 * np.pi * k / n_slots
        a1 = a0 + 2 * np.pi * (1 - slot_frac) / n_slots
        for y in (-0.615, -0.625):
            def face(U, V, y=y, a0=a0, a1=a1):
                ph = a0 + (a1 - a0) * U
                R = 0.55 + 0.25 * V
                return np.stack([R * np.cos(ph), np.full_like(R, y), R * np.sin(ph)], -1)
            out.append(_grid(face, 12, 4, uv_box=(0.55 + 0.07 * k, 0.5, 0.6 + 0.07 * k, 0.9)))
    return out


def atlas_image(size: int = 512) -> np.ndarray:
    """Texture atlas [size, 2 size, 3] uint8: astronaut (left), coffee (right)."""
    from PIL import Image
    from skimage import data
    left = Image.fromarray(data.astronaut()).resize((size, size), Image.LANCZOS)
    right = Image.fromarray(data.coffee()).resize((size, size), Image.LANCZOS)
    return np.concatenate([np.asarray(left), np.asarray(right)], axis=1)


def write_detail_mesh(directory: str | Path) -> Path:
    """Write ``detail.obj`` (+ ``detail.mtl`` naming the atlas PNG) into ``directory``."""
    import trimesh
    from PIL import Image

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    V, UV, F = _merge(detail_parts())
    image = Image.fromarray(atlas_image())
    mesh = trimesh.Trimesh(V, F, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=UV, image=image))
    obj = directory / "detail.obj"
    mesh.export(obj, file_type="obj", mtl_name="detail.mtl", include_normals=False)
    return obj
