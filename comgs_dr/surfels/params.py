"""Surfel data model: raw (optimisable) parameters of N 2D Gaussian surfels.

Storage is raw, activations are applied by :mod:`comgs_dr.surfels.kernel`:

===============  ============  =====================================================
field            type          meaning
===============  ============  =====================================================
means            Point3f [N]   centres p_i (world space)
quats            Vector4f [N]  rotation q_i, **w-first** (w, x, y, z), unnormalised
log_scales       Vector2f [N]  log of the two tangent-plane std. deviations s_u, s_v
opacity_logit    Float [N]     logit of the opacity o_i
sh               Float [N*K*3] SH colour coefficients, row-major [N, K, 3], K=(deg+1)^2
                               (3DGS convention: colour = max(SH(d)·f + 0.5, 0))
albedo           Color3f [N]   base colour a_i in [0, 1] (linear)
roughness        Float [N]     r_i in [0, 1]
metallic         Float [N]     m_i in [0, 1]
===============  ============  =====================================================

The normal of a surfel is the third column of R(q); tangents are the first two.
``to_numpy``/``from_numpy`` convert to a dict of float32 arrays shaped as in the
table (``sh`` as [N, K, 3]); both require an active JIT variant.
"""
from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels.kernel import SH_C0

NUMPY_SHAPES = {  # field -> trailing shape (after N)
    "means": (3,), "quats": (4,), "log_scales": (2,), "opacity_logit": (),
    "sh": None, "albedo": (3,), "roughness": (), "metallic": (),
}
MATERIAL_FIELDS = ("albedo", "roughness", "metallic")


def base_colour(sh) -> np.ndarray:
    """[N, 3] float the view-independent (degree-0) colour of SH coefficients ``sh`` [N, K, 3]
    (a ply's ``f_dc`` as [N, 1, 3] will do): 0.5 + SH_C0 · sh[:, 0], display values, not
    clipped (the 3DGS convention of the table above, at any view). Callers clip to what they
    need: [0, 1] for a colour, a floor above 0 for a logarithm."""
    sh = np.asarray(sh)
    if sh.ndim != 3 or sh.shape[2] != 3:
        raise ValueError(f"base_colour: SH coefficients must be [N, K, 3], got {sh.shape}")
    return 0.5 + SH_C0 * sh[:, 0]


def sh_from_base_colour(rgb) -> np.ndarray:
    """[N, 1, 3] float32 the degree-0 SH coefficients whose :func:`base_colour` is ``rgb``
    [N, 3] (display values): the inverse, (rgb − 0.5) / SH_C0."""
    rgb = np.asarray(rgb, np.float32)
    if rgb.ndim != 2 or rgb.shape[1] != 3:
        raise ValueError(f"sh_from_base_colour: colours must be [N, 3], got {rgb.shape}")
    return ((rgb - 0.5) / SH_C0)[:, None, :].astype(np.float32)


def sh_coeff_count(degree: int) -> int:
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    return (degree + 1) ** 2


def sh_degree_from_count(k: int) -> int:
    d = int(round(math.sqrt(k))) - 1
    if (d + 1) ** 2 != k or d not in (0, 1, 2, 3):
        raise ValueError(f"{k} SH coefficients per channel is not (degree+1)^2 for degree 0..3")
    return d


@dataclasses.dataclass
class SurfelParams:
    """Raw parameters of N surfels (a Dr.Jit PyTree: dr.eval/detach/grad work on it)."""
    means: object
    quats: object
    log_scales: object
    opacity_logit: object
    sh: object
    albedo: object
    roughness: object
    metallic: object

    # ------------------------------------------------------------------ info
    @property
    def count(self) -> int:
        return dr.width(self.opacity_logit)

    @property
    def sh_coeffs(self) -> int:
        n = self.count
        return dr.width(self.sh) // (3 * n) if n else 1

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_count(self.sh_coeffs)

    def __len__(self) -> int:
        return self.count

    def __repr__(self) -> str:
        return f"SurfelParams(N={self.count}, sh_degree={self.sh_degree})"

    # ----------------------------------------------------------- conversion
    @staticmethod
    def from_numpy(means, quats, log_scales, opacity_logit, sh, albedo=None,
                   roughness=None, metallic=None) -> "SurfelParams":
        """Build from arrays ([N,3], [N,4] w-first, [N,2], [N], [N,K,3] or [N,3], ...).

        Missing materials default to albedo 0.5, roughness 0.5, metallic 0.
        """
        means = _f32(means, "means", (3,))
        n = means.shape[0]
        quats = _f32(quats, "quats", (4,), n)
        log_scales = _f32(log_scales, "log_scales", (2,), n)
        opacity_logit = _f32(opacity_logit, "opacity_logit", (), n)
        sh = np.asarray(sh, dtype=np.float32)
        if sh.ndim == 2 and sh.shape[1] == 3:
            sh = sh[:, None, :]
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"sh: expected shape [N={n}, K, 3], got {list(sh.shape)}")
        sh_degree_from_count(sh.shape[1])
        albedo = np.full((n, 3), 0.5, np.float32) if albedo is None else _f32(albedo, "albedo", (3,), n)
        roughness = np.full(n, 0.5, np.float32) if roughness is None else _f32(roughness, "roughness", (), n)
        metallic = np.zeros(n, np.float32) if metallic is None else _f32(metallic, "metallic", (), n)
        return SurfelParams(
            means=to_jit(mi.Point3f, means.T), quats=to_jit(mi.Vector4f, quats.T),
            log_scales=to_jit(mi.Vector2f, log_scales.T),
            opacity_logit=to_jit(mi.Float, opacity_logit), sh=to_jit(mi.Float, sh.ravel()),
            albedo=to_jit(mi.Color3f, albedo.T), roughness=to_jit(mi.Float, roughness),
            metallic=to_jit(mi.Float, metallic))

    def to_numpy(self) -> dict:
        """Dict of float32 arrays ([N,3], [N,4], [N,2], [N], [N,K,3], [N,3], [N], [N])."""
        n = self.count
        out = {}
        for f in dataclasses.fields(self):
            a = np.asarray(dr.detach(getattr(self, f.name)), dtype=np.float32)
            if f.name == "sh":
                a = a.reshape(n, -1, 3)
            elif a.ndim == 2:
                a = a.T
            out[f.name] = np.ascontiguousarray(a)
        return out

    def copy(self) -> "SurfelParams":
        return SurfelParams(**{f.name: type(getattr(self, f.name))(getattr(self, f.name))
                               for f in dataclasses.fields(self)})

    def subset(self, index) -> "SurfelParams":
        """Surfels at the given indices (numpy int array or boolean mask)."""
        d = self.to_numpy()
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.nonzero(index)[0]
        return SurfelParams.from_numpy(**{k: v[index] for k, v in d.items()})

    @staticmethod
    def concat(parts: list["SurfelParams"]) -> "SurfelParams":
        ds = [p.to_numpy() for p in parts]
        k = max(d["sh"].shape[1] for d in ds)
        for d in ds:  # pad lower SH degrees with zeros
            if d["sh"].shape[1] < k:
                pad = np.zeros((d["sh"].shape[0], k - d["sh"].shape[1], 3), np.float32)
                d["sh"] = np.concatenate([d["sh"], pad], 1)
        return SurfelParams.from_numpy(**{key: np.concatenate([d[key] for d in ds], 0) for key in ds[0]})


def _f32(a, name, trailing, n=None) -> np.ndarray:
    a = np.asarray(a, dtype=np.float32)
    if a.ndim != 1 + len(trailing) or tuple(a.shape[1:]) != trailing or (n is not None and a.shape[0] != n):
        want = [n if n is not None else "N", *trailing]
        raise ValueError(f"{name}: expected shape {want}, got {list(a.shape)}")
    return a


def field_names() -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(SurfelParams))


def field_to_numpy(name: str, value, n: int) -> np.ndarray:
    """A SurfelParams field (or an Adam moment of it) as [N, ...] float32."""
    a = np.asarray(value, dtype=np.float32)
    if name == "sh":
        return a.reshape(n, -1)
    return a.T.copy() if a.ndim == 2 else a


def field_from_numpy(name: str, a: np.ndarray, like):
    """Inverse of :func:`field_to_numpy` with the Dr.Jit type of ``like``."""
    a = np.ascontiguousarray(a, dtype=np.float32)
    if name == "sh" or a.ndim == 1:
        return to_jit(type(like), a.ravel())
    return to_jit(type(like), a.T)


def object_size(params: SurfelParams) -> float:
    """Robust size of a surfel set: the diagonal of its centres' 0.5–99.5 percentile box
    (floaters do not count). The unit of step-2 offsets (probe and trace-ray offsets)."""
    pts = np.asarray(params.means).T                                       # [N, 3]
    if len(pts) == 0:
        raise ValueError("object_size: the surfel set is empty")
    return float(np.linalg.norm(np.percentile(pts, 99.5, 0) - np.percentile(pts, 0.5, 0)))


def object_bounds(params: SurfelParams, min_opacity: float = 0.1, q: float = 0.5):
    """World AABB (lo [3], hi [3]) of a surfel object: the ``q``–(100 − ``q``) percentile
    box of its surfels with opacity ≥ ``min_opacity`` (robust to stray floaters)."""
    means = np.asarray(dr.detach(params.means), np.float64).T                   # [N, 3]
    op = 1.0 / (1.0 + np.exp(-np.asarray(dr.detach(params.opacity_logit), np.float64)))
    m = means[(op >= min_opacity) & np.isfinite(means).all(1)]
    if len(m) == 0:
        raise ValueError(f"object_bounds: no surfel with a finite position and opacity ≥ "
                         f"{min_opacity}")
    return np.percentile(m, q, axis=0), np.percentile(m, 100 - q, axis=0)
