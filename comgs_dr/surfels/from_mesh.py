"""Surfels sampled on a triangle mesh (test scenes, initialisation, ground truth).

Positions are area-weighted uniform samples of the surface; each surfel lies in
its face's plane (t_u along the edge v0→v1, n = face normal by winding); its two
scales are σ = scale_factor · sqrt(A/(N·π)) · TILING, i.e. TILING times the radius
of a disc of the mean area per surfel. Albedo comes from the mesh texture
(bilinear, texels linearised with the sRGB transfer function), vertex/face
colours, or the material colour; the SH DC colour is the sRGB display value of
that albedo, DC = (srgb(albedo) − 0.5)/C0, so the radiance field shows the texture
as an sRGB image (3DGS convention).
"""
from __future__ import annotations

import dataclasses
import logging
import os

import numpy as np
from PIL import Image

from comgs_dr.core.colorspace import srgb_decode, srgb_encode
from comgs_dr.surfels.params import SurfelParams, sh_coeff_count, sh_from_base_colour

log = logging.getLogger(__name__)

# σ = TILING · sqrt(A/(Nπ)). Flat plane, N i.i.d. uniform samples, opacity 0.95: the mean
# composited weight W = 1 − Π(1 − α_i) is 0.857 (TILING 1.0), 0.935 (1.2), 0.975 (1.4),
# 0.985 (1.5), 0.998 (1.8) (`python tests/test_from_mesh.py`). Rendered with surfel_gbuffer
# (icosphere, 3000 surfels, 48², 4 seeds): mean W inside the silhouette 0.982. At 1.5 about
# 26 proxy quads (±3σ) overlap a point, below the G-buffer's default of 32 hits per ray.
TILING = 1.5
DEFAULT_GREY = 0.5


@dataclasses.dataclass
class MeshSampleInfo:
    """Where each surfel came from (``from_mesh(..., return_info=True)``)."""
    face_index: np.ndarray      # [N] int, index into the concatenated faces of all parts
    barycentric: np.ndarray     # [N, 3]
    face_areas: np.ndarray      # [F] areas of the concatenated faces
    sigma: float                # the surfel scale
    albedo_source: list         # per mesh part: "texture", "vertex_colors", "face_colors", "material", "default"


# --------------------------------------------------------------------- colour
def sample_texture(image, uv) -> np.ndarray:
    """Bilinear lookup of a PIL image at [N, 2] uv (v up, repeat wrap) -> [N, 3] linear RGB."""
    img = np.asarray(image.convert("RGB"), np.float64) / 255.0      # [H, W, 3] sRGB
    H, W = img.shape[:2]
    x = np.asarray(uv[:, 0], np.float64) * W - 0.5                  # texel centres at (i+0.5)/W
    y = (1.0 - np.asarray(uv[:, 1], np.float64)) * H - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)

    def tap(yy, xx):
        return srgb_decode(img[yy % H, xx % W])
    return ((1 - fy) * ((1 - fx) * tap(y0, x0) + fx * tap(y0, x0 + 1))
            + fy * ((1 - fx) * tap(y0 + 1, x0) + fx * tap(y0 + 1, x0 + 1)))


def _is_trimesh_placeholder(image) -> bool:
    """trimesh gives UV meshes without a material a 2×2 image of (100,100,100,255)."""
    if image is None or image.size != (2, 2):
        return False
    a = np.asarray(image.convert("RGBA"))
    return bool(np.all(a == np.array([100, 100, 100, 255], np.uint8)))


def _rgb01(c) -> np.ndarray:
    """trimesh colour (uint8 RGBA or floats in [0, 1]) -> [..., 3] floats in [0, 1]."""
    c = np.asarray(c)
    return c[..., :3] / 255.0 if c.dtype == np.uint8 or c.max(initial=0) > 1.0 else c[..., :3].astype(np.float64)


def _material_image(mat):
    img = getattr(mat, "baseColorTexture", None)
    img = getattr(mat, "image", None) if img is None else img
    return None if _is_trimesh_placeholder(img) else img


def _material_colour(mat):
    """Linear base colour of a material without texture, or None (trimesh's placeholder)."""
    bcf = getattr(mat, "baseColorFactor", None)                      # glTF PBR: linear
    if bcf is not None:
        return _rgb01(bcf)
    if _is_trimesh_placeholder(getattr(mat, "image", None)):
        return None                                                  # no MTL behind it
    diffuse = getattr(mat, "diffuse", None)                          # OBJ Kd: linear
    return None if diffuse is None else _rgb01(diffuse)


def _albedo(mesh, faces_local, bary, texture) -> tuple[np.ndarray, str]:
    """[M, 3] linear albedo for samples (face index within ``mesh``, barycentrics).

    Textures and vertex/face colours are sRGB-encoded (linearised here); material
    factors (glTF baseColorFactor, OBJ Kd) are linear. A glTF baseColorFactor
    multiplies its texture; an OBJ Kd does not (as Blender's importer).
    """
    vis = mesh.visual
    kind = getattr(vis, "kind", None)
    tri = mesh.faces[faces_local]                                    # [M, 3] vertex ids
    if kind == "texture":
        mat = vis.material
        image = texture if texture is not None else _material_image(mat)
        if image is not None and vis.uv is not None:
            uv = np.einsum("mk,mkj->mj", bary, np.asarray(vis.uv, np.float64)[tri])   # [M, 2]
            bcf = getattr(mat, "baseColorFactor", None)
            factor = _rgb01(bcf) if bcf is not None else np.ones(3)
            return sample_texture(image, uv) * factor, "texture"
        col = _material_colour(mat)
        if col is not None:
            return np.broadcast_to(col, (len(tri), 3)).copy(), "material"
    elif kind == "vertex":
        vc = srgb_decode(_rgb01(vis.vertex_colors))                # [V, 3]
        return np.einsum("mk,mkj->mj", bary, vc[tri]), "vertex_colors"
    elif kind == "face":
        return srgb_decode(_rgb01(vis.face_colors))[faces_local], "face_colors"
    return np.full((len(tri), 3), DEFAULT_GREY), "default"


# --------------------------------------------------------------------- geometry
def frame_to_quat(R) -> np.ndarray:
    """[N, 3, 3] rotations (columns t_u, t_v, n) -> [N, 4] w-first unit quaternions (Shepperd)."""
    R = np.asarray(R, np.float64)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    case = np.argmax(np.stack([m00 + m11 + m22, m00, m11, m22], 1), 1)
    q = np.empty((len(R), 4))
    d = {0: 1 + m00 + m11 + m22, 1: 1 + m00 - m11 - m22, 2: 1 - m00 + m11 - m22, 3: 1 - m00 - m11 + m22}
    for c in range(4):
        i = case == c
        r = R[i]
        s = 2.0 * np.sqrt(np.maximum(d[c][i], 1e-300))              # 4·(the large component)
        wx, wy, wz = r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]
        xy, xz, yz = r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1]
        q[i] = {0: lambda: np.stack([s / 4, wx / s, wy / s, wz / s], 1),
                1: lambda: np.stack([wx / s, s / 4, xy / s, xz / s], 1),
                2: lambda: np.stack([wy / s, xy / s, s / 4, yz / s], 1),
                3: lambda: np.stack([wz / s, xz / s, yz / s, s / 4], 1)}[c]()
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)                           # canonical: w ≥ 0
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _parts(mesh) -> list:
    """A path, Trimesh or Scene -> list of Trimesh in world coordinates."""
    import trimesh  # heavy (0.5 s): loaded when a mesh is sampled, not by `import comgs_dr`
    src = mesh
    if isinstance(mesh, (str, os.PathLike)):
        src = os.fspath(mesh)
        if not os.path.exists(src):
            raise FileNotFoundError(f"from_mesh: mesh file '{src}' not found")
        try:
            mesh = trimesh.load(src)
        except Exception as e:
            raise ValueError(f"from_mesh: cannot load '{src}' as a mesh ({type(e).__name__}: {e})") from e
    if isinstance(mesh, trimesh.Scene):
        parts = [g for g in mesh.dump() if isinstance(g, trimesh.Trimesh)]
    elif isinstance(mesh, trimesh.Trimesh):
        parts = [mesh]
    else:
        raise TypeError(f"from_mesh: expected a path, trimesh.Trimesh or trimesh.Scene, "
                        f"got {type(mesh).__name__}")
    parts = [p for p in parts if len(p.faces) > 0]
    if not parts:
        raise ValueError(f"from_mesh: {src if isinstance(src, str) else 'the mesh'} has no triangles")
    return parts


# --------------------------------------------------------------------- main entry
def from_mesh(mesh, n: int, *, seed: int = 0, opacity: float = 0.95, sh_degree: int = 0,
              roughness: float = 0.5, metallic: float = 0.0, scale_factor: float = 1.0,
              texture=None, return_info: bool = False):
    """N surfels tiling the surface of ``mesh`` (path, ``trimesh.Trimesh`` or ``trimesh.Scene``).

    ``texture`` (path or PIL image) overrides the base-colour texture of UV-mapped
    parts (e.g. an OBJ without ``mtllib``). Parts without colour get albedo 0.5 with
    a logged warning. Returns SurfelParams, or (SurfelParams, MeshSampleInfo) with
    ``return_info``. Materials: ``roughness``/``metallic`` constants in [0, 1].
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"from_mesh: n must be an integer, got {type(n).__name__}")
    if n < 1:
        raise ValueError(f"from_mesh: n must be ≥ 1, got {n}")
    if not 0.0 < opacity < 1.0:
        raise ValueError(f"from_mesh: opacity must be in (0, 1), got {opacity}")
    for name, v in (("roughness", roughness), ("metallic", metallic)):
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"from_mesh: {name} must be in [0, 1], got {v}")
    if not (scale_factor > 0 and np.isfinite(scale_factor)):
        raise ValueError(f"from_mesh: scale_factor must be > 0, got {scale_factor}")
    K = sh_coeff_count(sh_degree)
    if texture is not None and not hasattr(texture, "convert"):
        texture = Image.open(os.fspath(texture))

    parts = _parts(mesh)
    tris = np.concatenate([np.asarray(p.triangles, np.float64) for p in parts])   # [F, 3, 3]
    if not np.isfinite(tris).all():
        raise ValueError("from_mesh: the mesh has NaN/Inf vertex positions")
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]                     # [F, 3]
    cr = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(cr, axis=1)                                          # [F]
    area = np.where(area > 1e-12 * max(area.max(), 1e-300), area, 0.0)              # drop slivers
    total = float(area.sum())
    if not total > 0:
        raise ValueError("from_mesh: the mesh is degenerate (total surface area is 0)")

    # --- area-weighted sampling: faces ∝ area, uniform barycentrics (square folded onto the triangle)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(tris), size=n, p=area / total)                              # [N]
    uv = rng.random((n, 2))
    flip = uv.sum(1) > 1
    uv[flip] = 1 - uv[flip]
    bary = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)                # [N, 3]
    pos = np.einsum("nk,nkj->nj", bary, tris[face])                                  # [N, 3]

    # --- frames: t_u along v0->v1, n = face normal, t_v = n × t_u
    t_u = e1[face] / np.linalg.norm(e1[face], axis=1, keepdims=True)                 # [N, 3]
    nrm = cr[face] / np.linalg.norm(cr[face], axis=1, keepdims=True)
    t_v = np.cross(nrm, t_u)
    quats = frame_to_quat(np.stack([t_u, t_v, nrm], 2))                              # [N, 4]
    sigma = scale_factor * np.sqrt(total / (n * np.pi)) * TILING
    log_scales = np.full((n, 2), np.log(sigma))

    # --- albedo per part
    albedo = np.empty((n, 3))
    sources, offset = [], 0
    for p in parts:
        nf = len(p.faces)
        sel = (face >= offset) & (face < offset + nf)
        a, src = _albedo(p, face[sel] - offset, bary[sel], texture)
        albedo[sel] = a
        sources.append(src)
        offset += nf
    if "default" in sources:
        log.warning("from_mesh: %d of %d mesh part(s) have no texture or colours; "
                    "using albedo %.1f grey", sources.count("default"), len(parts), DEFAULT_GREY)
    albedo = np.clip(albedo, 0.0, 1.0)
    sh = np.zeros((n, K, 3))
    sh[:, 0] = sh_from_base_colour(srgb_encode(np.clip(albedo, 0.0, 1.0)))[:, 0]

    params = SurfelParams.from_numpy(
        means=pos, quats=quats, log_scales=log_scales,
        opacity_logit=np.full(n, np.log(opacity / (1 - opacity))), sh=sh, albedo=albedo,
        roughness=np.full(n, roughness), metallic=np.full(n, metallic))
    if not return_info:
        return params
    return params, MeshSampleInfo(face_index=face, barycentric=bary, face_areas=area,
                                  sigma=float(sigma), albedo_source=sources)
