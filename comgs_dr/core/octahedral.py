"""Octahedral maps: direction <-> square coordinates, bordered tile atlases, Jacobian.

Used by the environment map and by the Surface Octahedral Probes (paper, "Illumination
Modeling": both are stored as octahedral textures).

Mapping (Praun & Hoppe 2003): a unit direction d goes to
p = d.xy / |d|₁ ∈ [-1, 1]²; the lower hemisphere (d.z < 0) is folded into the corners,
p ← (1 − |p.yx|)·sign(p). Texture coordinates are uv = (p + 1)/2; texel (i, j) of an R×R
tile has its centre at ((i + 0.5)/R, (j + 0.5)/R).

Atlas layout: P tiles, each stored with a 1-texel border, i.e. (R+2)×(R+2) texels of C
channels, flat and row-major: ``atlas[((tile·(R+2) + y)·(R+2) + x)·C + c]``. The border
holds copies of the texels that lie beyond the octahedron's edges (the square's edges are
mirrored about their midpoints and its four corners all map to −Z), so a bilinear lookup
never needs a branch and is continuous across every seam.

Solid angle: with q(p) the L1-normalised direction before normalisation (|q|₁ = 1 in both
hemispheres), dω = dp / |q|₂³ exactly, so dω/d(uv) = 4 / |q|₂³ (it integrates to 4π; texels
near the octahedron's vertices subtend ≈ 3√3 ≈ 5.2× the solid angle of texels at the face
centres).
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit

# ---------------------------------------------------------------------------------------
# Direction <-> octahedral square (Dr.Jit, any JIT variant, differentiable)

def _sign(x):
    return dr.select(x >= 0, 1.0, -1.0)


def dir_to_oct(d):
    """Unit direction ``mi.Vector3f`` -> ``mi.Point2f`` p ∈ [-1, 1]²."""
    l1 = dr.maximum(dr.abs(d.x) + dr.abs(d.y) + dr.abs(d.z), 1e-30)
    px, py = d.x / l1, d.y / l1
    lower = d.z < 0
    fx = (1.0 - dr.abs(py)) * _sign(px)
    fy = (1.0 - dr.abs(px)) * _sign(py)
    return mi.Point2f(dr.select(lower, fx, px), dr.select(lower, fy, py))


def oct_to_dir_unnormalized(p):
    """p ∈ [-1, 1]² -> q with |q|₁ = 1 (the un-normalised direction)."""
    z = 1.0 - dr.abs(p.x) - dr.abs(p.y)
    lower = z < 0
    fx = (1.0 - dr.abs(p.y)) * _sign(p.x)
    fy = (1.0 - dr.abs(p.x)) * _sign(p.y)
    return mi.Vector3f(dr.select(lower, fx, p.x), dr.select(lower, fy, p.y), z)


def oct_to_dir(p):
    """p ∈ [-1, 1]² -> unit direction ``mi.Vector3f``."""
    return dr.normalize(oct_to_dir_unnormalized(p))


def dir_to_uv(d):
    p = dir_to_oct(d)
    return mi.Point2f(0.5 * (p.x + 1.0), 0.5 * (p.y + 1.0))


def uv_to_dir(uv):
    return oct_to_dir(mi.Point2f(2.0 * uv.x - 1.0, 2.0 * uv.y - 1.0))


def jacobian_uv(uv):
    """dω / d(uv) at ``uv`` (exact): 4 / |q|₂³."""
    q = oct_to_dir_unnormalized(mi.Point2f(2.0 * uv.x - 1.0, 2.0 * uv.y - 1.0))
    n2 = dr.squared_norm(q)
    return 4.0 / (n2 * dr.sqrt(n2))


# NumPy twins (used to build tables and by tests) -------------------------------------------

def dir_to_uv_np(d):
    """[N, 3] unit directions -> [N, 2] uv."""
    d = np.asarray(d, np.float64)
    l1 = np.maximum(np.abs(d).sum(-1, keepdims=True), 1e-300)
    p = d[:, :2] / l1
    s = np.where(p >= 0, 1.0, -1.0)
    f = (1.0 - np.abs(p[:, ::-1])) * s
    p = np.where((d[:, 2] < 0)[:, None], f, p)
    return 0.5 * (p + 1.0)


def uv_to_dir_np(uv):
    """[N, 2] uv -> [N, 3] unit directions."""
    p = 2.0 * np.asarray(uv, np.float64) - 1.0
    z = 1.0 - np.abs(p).sum(-1)
    s = np.where(p >= 0, 1.0, -1.0)
    f = (1.0 - np.abs(p[:, ::-1])) * s
    xy = np.where((z < 0)[:, None], f, p)
    q = np.concatenate([xy, z[:, None]], -1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def texel_directions_np(res: int) -> np.ndarray:
    """Directions of the R×R texel centres, [R*R, 3] row-major (y, x)."""
    c = (np.arange(res) + 0.5) / res
    u, v = np.meshgrid(c, c)                 # [R, R] each; u along x (columns)
    return uv_to_dir_np(np.stack([u.ravel(), v.ravel()], -1))


def texel_solid_angles_np(res: int, sub: int = 8) -> np.ndarray:
    """Solid angle of each texel of an R×R map, [R*R] row-major, by sub×sub midpoint
    integration of the exact Jacobian (sums to 4π within ~1e-4 relative for sub=8).
    Cached per (R, sub) (0.4 s at R = 256; env-map sampling tables are rebuilt per step)."""
    return _texel_solid_angles(int(res), int(sub)).copy()


@functools.lru_cache(maxsize=8)
def _texel_solid_angles(res: int, sub: int) -> np.ndarray:
    c = (np.arange(res * sub) + 0.5) / (res * sub)
    u, v = np.meshgrid(c, c)
    p = 2.0 * np.stack([u, v], -1) - 1.0
    z = 1.0 - np.abs(p).sum(-1)
    s = np.where(p >= 0, 1.0, -1.0)
    f = (1.0 - np.abs(p[..., ::-1])) * s
    xy = np.where((z < 0)[..., None], f, p)
    n = np.sqrt((xy ** 2).sum(-1) + z ** 2)
    jac = 4.0 / n ** 3 / (res * sub) ** 2      # dω per sub-texel
    return jac.reshape(res, sub, res, sub).sum((1, 3)).ravel()


# ---------------------------------------------------------------------------------------
# Bordered tiles

def border_source_index(res: int) -> np.ndarray:
    """For each texel of a bordered (R+2)² tile, the interior texel (y·R + x) it copies.

    Interior texels copy themselves. Beyond the top/bottom edge the column is mirrored
    (x -> R−1−x), beyond the left/right edge the row is mirrored, and the four corner
    border texels copy the diagonally opposite interior corner (all corners map to −Z).
    """
    b = res + 2
    src = np.empty((b, b), np.int64)
    for yb in range(b):
        for xb in range(b):
            x, y = xb - 1, yb - 1
            if y < 0:
                x, y = res - 1 - x, 0
            elif y >= res:
                x, y = res - 1 - x, res - 1
            if x < 0:
                x, y = 0, res - 1 - y
            elif x >= res:
                x, y = res - 1, res - 1 - y
            src[yb, xb] = y * res + x
    return src.ravel()


def add_border_np(tiles: np.ndarray) -> np.ndarray:
    """[P, R, R, C] -> [P, R+2, R+2, C] with the octahedral wrap border filled."""
    tiles = np.asarray(tiles)
    p, r, r2, c = tiles.shape
    if r != r2:
        raise ValueError(f"octahedral tiles must be square, got {r}x{r2}")
    flat = tiles.reshape(p, r * r, c)
    return flat[:, border_source_index(r)].reshape(p, r + 2, r + 2, c)


def strip_border_np(bordered: np.ndarray) -> np.ndarray:
    """[P, R+2, R+2, C] -> [P, R, R, C]."""
    return np.asarray(bordered)[:, 1:-1, 1:-1]


def border_gather_index(n_tiles: int, res: int) -> np.ndarray:
    """Flat texel index (into a bordered atlas) that every bordered texel copies, [P*(R+2)²]."""
    b2 = (res + 2) ** 2
    src = border_source_index(res)
    ys, xs = src // res + 1, src % res + 1
    local = ys * (res + 2) + xs
    return (np.arange(n_tiles)[:, None] * b2 + local[None, :]).ravel()


class BorderRefresher:
    """Re-copies the wrap border of a flat bordered atlas in place (after an optimiser step).

    Keeping the *bordered* atlas as the optimised parameter and refreshing its border
    outside the differentiated graph is faster than building the border inside
    the graph; the gradient that bilinear lookups put on border texels is dropped by it.
    """

    def __init__(self, n_tiles: int, res: int, channels: int):
        idx = border_gather_index(n_tiles, res)                        # [P*(R+2)²]
        full = (idx[:, None] * channels + np.arange(channels)[None]).ravel()
        self.index = to_jit(mi.UInt32, full)
        self.size = n_tiles * (res + 2) ** 2 * channels

    def __call__(self, atlas):
        if dr.width(atlas) != self.size:
            raise ValueError(f"atlas has {dr.width(atlas)} values, expected {self.size}")
        out = dr.gather(type(atlas), dr.detach(atlas), self.index)
        dr.eval(out)
        return out


class BorderGather:
    """Interior tiles [P, R, R, C] (flat) -> the bordered atlas [P, R+2, R+2, C] (flat), as one
    differentiable gather: the adjoint adds the gradient of every border texel onto the
    interior texel it copies (so texels next to seams learn like the others)."""

    def __init__(self, n_tiles: int, res: int, channels: int):
        src = border_source_index(res)                                   # [(R+2)²]
        texel = (np.arange(n_tiles)[:, None] * res * res + src[None, :]).ravel()
        full = (texel[:, None] * channels + np.arange(channels)[None]).ravel()
        self.index = to_jit(mi.UInt32, full)
        self.size = n_tiles * res * res * channels

    def __call__(self, interior):
        if dr.width(interior) != self.size:
            raise ValueError(f"interior atlas has {dr.width(interior)} values, expected {self.size}")
        return dr.gather(type(interior), interior, self.index)


# ---------------------------------------------------------------------------------------
# Bilinear lookup into a bordered atlas (Dr.Jit, differentiable w.r.t. the atlas)

class Taps:
    """Flat texel indices and bilinear weights of a lookup; reusable across atlases of the
    same layout (tile count, R) and channel count."""

    def __init__(self, index, weight):
        self.index = index      # 4 × mi.UInt32 (texel index in the bordered atlas)
        self.weight = weight    # 4 × mi.Float


def bilinear_taps(tile, uv, res: int) -> Taps:
    """Texel indices/weights for a bilinear lookup at ``uv`` ∈ [0,1]² of tile ``tile``
    (``mi.UInt32``) of a bordered atlas with R×R interior texels."""
    b = res + 2
    # Continuous bordered-texel coordinate with texel centres at integers: interior texel
    # i (bordered index i + 1) sits at i + 1, i.e. x = uv·R + 0.5.
    x = dr.clip(uv.x, 0.0, 1.0) * res + 0.5
    y = dr.clip(uv.y, 0.0, 1.0) * res + 0.5
    x0f, y0f = dr.floor(x), dr.floor(y)
    fx, fy = x - x0f, y - y0f
    x0 = dr.minimum(mi.UInt32(x0f), res)            # ∈ [0, R]; +1 stays inside the border
    y0 = dr.minimum(mi.UInt32(y0f), res)
    base = (tile * b + y0) * b + x0
    index = [base, base + 1, base + b, base + b + 1]
    weight = [(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]
    return Taps(index, weight)


def nearest_taps(tile, uv, res: int) -> Taps:
    """One-tap (nearest-texel) lookup of a bordered atlas; same interface as
    :func:`bilinear_taps` (4× fewer gathers and backward scatter-adds)."""
    b = res + 2
    x = dr.minimum(mi.UInt32(dr.clip(uv.x, 0.0, 1.0) * res), res - 1) + 1
    y = dr.minimum(mi.UInt32(dr.clip(uv.y, 0.0, 1.0) * res), res - 1) + 1
    return Taps([(tile * b + y) * b + x], [mi.Float(1.0)])


_VEC = {1: "Float", 3: "Color3f", 4: "Vector4f"}


def expand_mode(source):
    """``ReduceMode.Expand`` for sources that need gradients (fast backward scatter-add),
    the default otherwise: Expand-mode gathers from *non-differentiable*
    sources inside a graph that is later differentiated were seen to segfault Dr.Jit 1.5."""
    return dr.ReduceMode.Expand if dr.grad_enabled(source) else dr.ReduceMode.Auto


def lookup(atlas, taps: Taps, channels: int):
    """Bilinear lookup of a ``channels``-wide atlas (1, 3 or 4): ``mi.Float``,
    ``mi.Color3f`` or ``mi.Vector4f``.

    One vector gather per tap, with ``ReduceMode.Expand`` so the backward scatter-add is
    fast.
    """
    if channels not in _VEC:
        raise ValueError(f"atlas lookups support 1, 3 or 4 channels, got {channels}")
    cls = getattr(mi, _VEC[channels])
    mode = expand_mode(atlas)
    out = None
    for idx, w in zip(taps.index, taps.weight):
        v = dr.gather(cls, atlas, idx, mode=mode)
        out = w * v if out is None else out + w * v
    return out


def lookup_nearest(atlas, tile, uv, res: int, channels: int):
    """Nearest-texel lookup (for sampling tables and tests)."""
    b = res + 2
    x = dr.minimum(mi.UInt32(dr.clip(uv.x, 0.0, 1.0) * res), res - 1) + 1
    y = dr.minimum(mi.UInt32(dr.clip(uv.y, 0.0, 1.0) * res), res - 1) + 1
    idx = (tile * b + y) * b + x
    if channels not in _VEC:
        raise ValueError(f"atlas lookups support 1, 3 or 4 channels, got {channels}")
    return dr.gather(getattr(mi, _VEC[channels]), atlas, idx)
