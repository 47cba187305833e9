"""Learnable octahedral environment map with exact importance sampling.

Paper, "Illumination Modeling": direct light L_dir is a learnable environment map stored as
an octahedral texture (256² in sec. 4.1). Here the map is parameterised by its log radiance
θ (positive radiance exp θ, scale-free Adam steps, HDR up to ~1e6 without overflow), kept
as a bordered atlas (``core.octahedral``) so bilinear lookups are seamless.

Importance sampling picks a texel with probability ∝ luminance × texel solid angle (plus a
small floor so every direction has pdf > 0), then a uniform point inside it. The solid-angle
pdf is **exact**: pdf(ω) = P[texel]·R² / (dω/duv), with the octahedral Jacobian
dω/duv = 4/|q|³ (the paper approximates texels as equal-area).

Equirect convention (as the dataset generator, Blender's Z-up): u = 0.5 − atan2(d_y, d_x)/2π,
v = acos(d_z)/π, v = 0 the top row.
"""
from __future__ import annotations

import logging
import warnings

from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.ndimage import maximum_filter

from comgs_dr.core import exr, rgbe
from comgs_dr.core import octahedral as octa
from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.equirect import (
    equirect_dir_to_uv_np,
    equirect_uv_to_dir_np,
    sample_equirect_np,
)
from comgs_dr.core.hostarray import to_jit

log = logging.getLogger(__name__)
# Negative values no deeper than this × the map's mean are compression noise (the shared
# Blender maps, DWAB-compressed: down to 0.0144 × the mean in blender_night): clamped with
# an info line, not a warning; deeper ones (a damaged or mis-encoded file) warn.
NEGATIVE_NOISE = 0.05

LOG_RANGE = (-16.0, 16.0)    # clamp of log radiance: exp(±16) ≈ 1e-7 .. 9e6


# ---------------------------------------------------------------------------------------
# Equirect <-> octahedral (NumPy)

def equirect_to_oct_np(img, res: int, sub: int = 4) -> np.ndarray:
    """Resample an [H, W, 3] equirect map to an [R, R, 3] octahedral map.

    Energy-preserving: when the equirect map is at least 4R wide, every equirect pixel's
    radiance × solid angle is binned into the texel holding its centre and divided by the
    texel's solid angle (a sun of a few pixels keeps its power); texels that receive no
    pixel, and all texels of smaller maps, use the mean of sub×sub bilinear samples.
    """
    img = np.asarray(img, np.float64)[..., :3]
    h, w = img.shape[:2]
    c = (np.arange(res * sub) + 0.5) / (res * sub)
    u, v = np.meshgrid(c, c)
    d = octa.uv_to_dir_np(np.stack([u.ravel(), v.ravel()], -1))
    ss = sample_equirect_np(img, equirect_dir_to_uv_np(d))
    out = ss.reshape(res, sub, res, sub, 3).mean((1, 3)).reshape(res * res, 3)
    if w >= 4 * res:
        ex, ey = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
        dirs = equirect_uv_to_dir_np(np.stack([ex.ravel(), ey.ravel()], -1))
        sin_t = np.sin((np.arange(h) + 0.5) / h * np.pi)
        d_omega = np.repeat(sin_t, w) * (2 * np.pi / w) * (np.pi / h)     # [H*W]
        tuv = octa.dir_to_uv_np(dirs)
        t = (np.minimum((tuv[:, 1] * res).astype(np.int64), res - 1) * res
             + np.minimum((tuv[:, 0] * res).astype(np.int64), res - 1))
        area = np.bincount(t, d_omega, res * res)
        flat = img.reshape(-1, 3)
        acc = np.stack([np.bincount(t, flat[:, k] * d_omega, res * res) for k in range(3)], -1)
        have = area > 0
        out[have] = acc[have] / area[have, None]      # solid-angle-weighted mean radiance
    return out.reshape(res, res, 3)


def oct_to_equirect_np(oct_img, width: int) -> np.ndarray:
    """[R, R, 3] octahedral map -> [width/2, width, 3] equirect (bilinear, seamless)."""
    oct_img = np.asarray(oct_img, np.float64)
    res = oct_img.shape[0]
    h = width // 2
    ex, ey = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(h) + 0.5) / h)
    d = equirect_uv_to_dir_np(np.stack([ex.ravel(), ey.ravel()], -1))
    bordered = octa.add_border_np(oct_img[None])[0]                     # [R+2, R+2, 3]
    uv = octa.dir_to_uv_np(d)
    x = np.clip(uv[:, 0], 0, 1) * res + 0.5
    y = np.clip(uv[:, 1], 0, 1) * res + 0.5
    x0 = np.minimum(np.floor(x).astype(np.int64), res)
    y0 = np.minimum(np.floor(y).astype(np.int64), res)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    val = ((1 - fx) * (1 - fy) * bordered[y0, x0] + fx * (1 - fy) * bordered[y0, x0 + 1]
           + (1 - fx) * fy * bordered[y0 + 1, x0] + fx * fy * bordered[y0 + 1, x0 + 1])
    return val.reshape(h, width, 3)


# ---------------------------------------------------------------------------------------
# Files

def read_envmap_file(path) -> tuple[np.ndarray, str]:
    """Read an .exr/.hdr map: (float64 [H, W, 3] radiance, layout 'equirect'|'octahedral').

    The layout comes from the file's ``layout`` metadata when present (files we write),
    otherwise from the shape (2:1 equirect; square maps are rejected as ambiguous).
    NaN/Inf or negative values raise ValueError naming the file and the count.
    """
    p = Path(path)
    rgb, attrs = _read_checked(p)
    arr = rgb.astype(np.float64)
    layout = attrs.get("layout")
    if layout is None:
        h, w = arr.shape[:2]
        if w == 2 * h:
            layout = "equirect"
        else:
            raise ValueError(f"environment map {p}: cannot tell its layout from a {w}x{h} "
                             "image without 'layout' metadata (expected a 2:1 equirect map)")
    if layout not in ("equirect", "octahedral"):
        raise ValueError(f"environment map {p}: unknown layout metadata {layout!r}")
    return arr, layout


def oct_radiance_from_file(path, res: int, scale: float = 1.0) -> np.ndarray:
    """[res, res, 3] octahedral radiance × ``scale`` of an equirect or octahedral map file
    (``read_envmap_file``); octahedral maps of another size are resampled through a fine
    equirect. Not clamped to ``LOG_RANGE``."""
    arr, layout = read_envmap_file(path)
    if layout == "equirect":
        return equirect_to_oct_np(arr * scale, res)
    if arr.shape[0] != res:
        arr = equirect_to_oct_np(oct_to_equirect_np(arr, 4 * max(res, arr.shape[0])), res)
    return arr * scale


def write_exr(path, img: np.ndarray, layout: str) -> Path:
    """Write a linear RGB float EXR with ``layout`` (and our conventions) in its metadata."""
    conv = ("octahedral: d.xy/|d|_1, lower hemisphere folded, Z-up" if layout == "octahedral"
            else "equirect: u=0.5-atan2(y,x)/2pi, v=acos(z)/pi, Z-up")
    return exr.write_image(path, np.asarray(img)[..., :3],
                           {"layout": layout, "convention": conv})


# ---------------------------------------------------------------------------------------
# The learnable map

class OctEnvmap:
    """Octahedral environment map, R×R texels, radiance exp θ (θ the optimised parameter).

    ``theta`` is a flat bordered atlas (1 tile, 3 channels); after each optimiser step call
    :meth:`refresh` (clamps θ to ``LOG_RANGE`` and re-copies the wrap border).
    """

    def __init__(self, radiance: np.ndarray):
        radiance = np.asarray(radiance, np.float64)
        if radiance.ndim != 3 or radiance.shape[0] != radiance.shape[1] or radiance.shape[2] != 3:
            raise ValueError(f"octahedral map must be [R, R, 3], got {radiance.shape}")
        if not np.all(np.isfinite(radiance)) or (radiance < 0).any():
            raise ValueError("environment radiance must be finite and non-negative "
                             f"({int((~np.isfinite(radiance)).sum())} non-finite, "
                             f"{int((radiance < 0).sum())} negative values)")
        self.res = radiance.shape[0]
        log = np.clip(np.log(np.maximum(radiance, np.exp(LOG_RANGE[0]))), *LOG_RANGE)
        self.theta = to_jit(mi.Float, octa.add_border_np(log[None]).ravel())
        self._border = octa.BorderRefresher(1, self.res, 3)

    # construction ------------------------------------------------------------------------
    @classmethod
    def constant(cls, res: int = 256, value=0.5):
        return cls(np.broadcast_to(np.asarray(value, np.float64), (res, res, 3)).copy())

    @classmethod
    def from_equirect(cls, img, res: int = 256, scale: float = 1.0):
        return cls(equirect_to_oct_np(np.asarray(img) * scale, res))

    @classmethod
    def from_file(cls, path, res: int = 256, scale: float = 1.0):
        return cls(oct_radiance_from_file(path, res, scale))

    # state -------------------------------------------------------------------------------
    def refresh(self):
        """Clamp θ and restore the wrap border (call after every optimiser step)."""
        self.theta = self._border(dr.clip(dr.detach(self.theta), *LOG_RANGE))
        self._sampler = None

    def radiance_np(self) -> np.ndarray:
        """Interior radiance, [R, R, 3] float64."""
        r = self.res
        th = np.array(dr.detach(self.theta), np.float64).reshape(r + 2, r + 2, 3)
        return np.exp(th[1:-1, 1:-1])

    def save(self, path, equirect_width: int | None = None) -> Path:
        """Octahedral EXR (default) or, with ``equirect_width``, an equirect EXR."""
        rad = self.radiance_np()
        if equirect_width:
            return write_exr(path, oct_to_equirect_np(rad, equirect_width), "equirect")
        return write_exr(path, rad, "octahedral")

    # evaluation --------------------------------------------------------------------------
    def eval(self, d, theta=None):
        """Radiance arriving from world direction ``d`` (``mi.Vector3f``) -> ``mi.Color3f``.
        Differentiable w.r.t. ``theta`` (defaults to ``self.theta``)."""
        theta = self.theta if theta is None else theta
        taps = octa.bilinear_taps(mi.UInt32(0), octa.dir_to_uv(d), self.res)
        radiance = dr.exp(theta)
        # Evaluated before the Expand-mode gathers: their backward pass into an unevaluated
        # source was seen to crash Dr.Jit 1.5 (segfault in the next kernel launch).
        dr.eval(radiance)
        return octa.lookup(radiance, taps, 3)

    def eval_world(self, d, theta=None):
        """The shading code's interface (as ``octenvmap``'s): :meth:`eval`."""
        return self.eval(d, theta)

    def sampler(self, floor: float = 1e-3) -> "EnvSampler":
        return EnvSampler(self.radiance_np(), floor)

    def _cached_sampler(self) -> "EnvSampler":
        if getattr(self, "_sampler", None) is None:      # rebuilt after refresh()
            self._sampler = self.sampler()
        return self._sampler

    def sample_world(self, u):
        """(direction, solid-angle pdf) ∝ the current map's luminance (:class:`EnvSampler`)."""
        s = self._cached_sampler().sample(u)
        return s.direction, s.pdf

    def pdf_world(self, d):
        return self._cached_sampler().pdf(d)


@dataclass
class EnvSample:
    direction: object   # mi.Vector3f
    pdf: object         # mi.Float, solid-angle density


class EnvSampler:
    """Texel-intensity importance sampling of an [R, R, 3] octahedral map (exact pdf).

    Texel probability ∝ (3×3 max of the luminance)·solid angle + ``floor``·(mean of that) so
    no direction has zero density; within a texel the point is uniform in uv.
    """

    def __init__(self, radiance: np.ndarray, floor: float = 1e-3):
        r = radiance.shape[0]
        self.res = r
        lum = np.maximum(np.asarray(radiance, np.float64) @ LUMA, 0.0)          # [R, R]
        # Lookups are bilinear, so a texel next to a bright one returns up to ~its value:
        # the weight is the 3×3 maximum (across the seams, via the wrap border), so the
        # ratio radiance/pdf stays bounded (a one-texel sun otherwise gave fireflies).
        bordered = octa.add_border_np(lum[None, ..., None])[0, ..., 0]          # [R+2, R+2]
        lum = maximum_filter(bordered, size=3, mode="nearest")[1:-1, 1:-1].ravel()
        w = lum * octa.texel_solid_angles_np(r)
        w = w + floor * max(w.mean(), 1e-30)
        if not np.all(np.isfinite(w)) or w.sum() <= 0:
            raise ValueError("environment map has no finite positive energy to sample")
        self.pmf_np = w / w.sum()
        self.dist = mi.DiscreteDistribution(to_jit(mi.Float, self.pmf_np))
        self.pmf = to_jit(mi.Float, self.pmf_np)

    def sample(self, u) -> EnvSample:
        """``u``: ``mi.Point2f`` in [0,1)² -> direction and solid-angle pdf."""
        idx, ux = self.dist.sample_reuse(u.x)
        r = self.res
        tx, ty = idx % r, idx // r
        uv = mi.Point2f((mi.Float(tx) + ux) / r, (mi.Float(ty) + u.y) / r)
        d = octa.uv_to_dir(uv)
        pmf = dr.gather(mi.Float, self.pmf, idx)
        return EnvSample(d, pmf * (r * r) / octa.jacobian_uv(uv))

    def pdf(self, d):
        r = self.res
        uv = octa.dir_to_uv(d)
        tx = dr.minimum(mi.UInt32(uv.x * r), r - 1)
        ty = dr.minimum(mi.UInt32(uv.y * r), r - 1)
        pmf = dr.gather(mi.Float, self.pmf, ty * r + tx)
        return pmf * (r * r) / octa.jacobian_uv(uv)


def _read_checked(p: Path) -> tuple[np.ndarray, dict]:
    """(float32 [H, W, 3] radiance, string metadata) of an environment map file: EXR through
    ``core.exr``, other formats (.hdr, .pfm) through ``mi.Bitmap``. Errors as
    :func:`load_envmap`."""
    if not p.is_file():
        raise FileNotFoundError(f"environment map not found: {p}")
    attrs = {}
    try:
        if p.suffix.lower() == ".exr":
            arr, attrs = exr.read_image(p), exr.read_attrs(p)
        else:
            with open(p, "rb") as f:
                if f.read(2) == b"#?":      # Radiance RGBE: Mitsuba crashes on damaged RLE
                    rgbe.check_rgbe(p)
            bmp = mi.Bitmap(str(p))
            fmt = bmp.component_format()
            arr = np.array(bmp, copy=True)
    except Exception as e:  # Mitsuba raises RuntimeError with its own wording
        raise ValueError(f"cannot read environment map {p}: {e}") from e
    else:
        if p.suffix.lower() != ".exr" and fmt not in (mi.Struct.Type.Float16,
                                                      mi.Struct.Type.Float32,
                                                      mi.Struct.Type.Float64):
            # a PNG / JPEG holds display values (sRGB, 0–255), not radiance: read as
            # radiance it would light a scene ~250× too bright and without its lights
            raise ValueError(f"environment map {p} is an integer "
                             f"({getattr(fmt, 'name', str(fmt))}) image: it holds "
                             f"display values, not radiance. Give a linear HDR map (.exr or "
                             f".hdr); a photo's clipped lights cannot be recovered from it")
    if arr.ndim != 3 or arr.shape[2] not in (3, 4) or min(arr.shape[:2]) < 2:
        raise ValueError(f"environment map {p} must be an RGB(A) image of at least 2x2 "
                         f"pixels, got shape {arr.shape}")
    rgb = np.ascontiguousarray(arr[..., :3], np.float32)
    bad = int(np.count_nonzero(~np.isfinite(rgb)))
    if bad:
        raise ValueError(f"environment map {p} has {bad} non-finite (NaN/Inf) values")
    neg = int(np.count_nonzero(rgb < 0))
    if neg:
        msg = (f"environment map {p}: {neg} negative values (most negative "
               f"{float(rgb.min()):.3g}) clamped to 0")
        if -float(rgb.min()) <= NEGATIVE_NOISE * float(np.mean(np.maximum(rgb, 0.0))):
            log.info(msg)           # lossy EXR compression (DWAB): noise around black
        else:
            warnings.warn(msg, stacklevel=3)
        rgb = np.maximum(rgb, 0.0)
    return rgb, attrs


def load_envmap(path):
    """Read an HDR/EXR environment map as a float32 RGB ``mi.Bitmap``, checking its values.

    FileNotFoundError if missing; ValueError if unreadable, not RGB(A), or holding NaN/Inf
    values (the message names the file and the count). Negative values, which lossy EXR
    compression (DWAA/DWAB, as in Blender's shipped maps) leaves in dark texels, are clamped
    to 0 with a warning that names their count and the most negative one.
    """
    rgb, _ = _read_checked(Path(path))
    return mi.Bitmap(rgb, pixel_format=mi.Bitmap.PixelFormat.RGB)
