"""Equirectangular panoramas of a surfel scene seen from one point (no AD).

For every pixel of an H×W equirect image, rays leave ``position`` and the surfels along them
are composited front to back (:func:`comgs_dr.surfels.composite.trace_composite`), giving coverage
W = 1 − T, the radiance-field colour, the depth and the normal of what surrounds the point
(e.g. the lighting / occlusion environment of an object to be inserted there).

Direction convention (as :mod:`comgs_dr.lighting.envmap`, Blender's Z-up equirect):
u = 0.5 − atan2(d_y, d_x)/2π, v = acos(d_z)/π, v = 0 the top row (+Z); pixel (i, j) has its
centre at u = (i + 0.5)/W, v = (j + 0.5)/H. So +X is at the image centre (u = v = 0.5) and +Y
at u = 0.25.

Outputs are un-premultiplied (divided by W) where W ≥ ``W_EPS`` and 0 elsewhere; ``alpha``
(= W) is the coverage mask. With ``supersample = s`` every pixel averages s×s jittered
stratified rays: the premultiplied buffers (W·colour, W·depth, W·normal, W·linear radiance)
are averaged, then divided by the averaged W.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core import colorspace
from comgs_dr.core.equirect import coverage, equirect_directions, pixel_directions
from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels import composite
from comgs_dr.surfels.composite import trace_composite
from comgs_dr.surfels.shape import SurfelShapeBase, ensure_proxies

log = logging.getLogger(__name__)

CONVENTION = ("equirect: u=0.5-atan2(y,x)/2pi, v=acos(z)/pi, Z-up, v=0 top row, "
              "pixel centres ((i+0.5)/W, (j+0.5)/H)")
W_EPS = 1e-4          # below this coverage a pixel's colour/depth/normal are reported as 0
BBOX_MARGIN = 0.1     # the position may lie this fraction of the bbox diagonal outside it


@dataclass
class PanoramaConfig:
    """Settings of :func:`trace_panorama`.

    ``exclude_radius`` > 0 leaves out every surfel whose centre lies within that distance of
    the position (the inserted object itself and its footprint). ``colour_space``: the space
    the radiance field's colour was fitted in ('srgb' or 'linear'). ``seed`` drives the
    sub-pixel jitter when ``supersample`` > 1.
    """
    width: int = 1024
    height: int = 512
    max_hits: int = 32
    exclude_radius: float = 0.0
    colour_space: str = "srgb"
    supersample: int = 1
    seed: int = 0

    def validate(self) -> None:
        for name in ("width", "height", "max_hits", "supersample"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"PanoramaConfig.{name} must be an integer ≥ 1, got {v!r}")
        r = self.exclude_radius
        if not (isinstance(r, (int, float, np.floating, np.integer)) and np.isfinite(r) and r >= 0):
            raise ValueError(f"PanoramaConfig.exclude_radius must be finite and ≥ 0, got {r!r}")
        if self.colour_space not in ("srgb", "linear"):
            raise ValueError("PanoramaConfig.colour_space must be 'srgb' or 'linear', "
                             f"got {self.colour_space!r}")


# ---------------------------------------------------------------------------------------
# NumPy helpers







# ---------------------------------------------------------------------------------------
# Scene handling

def _check_position(position, bbox_min, bbox_max) -> np.ndarray:
    p = np.asarray(position, dtype=np.float64)
    if p.shape != (3,):
        raise ValueError(f"trace_panorama: position must be 3 values (x, y, z), got shape "
                         f"{list(p.shape)}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"trace_panorama: position must be finite, got {p.tolist()}")
    margin = BBOX_MARGIN * float(np.linalg.norm(bbox_max - bbox_min))
    lo, hi = bbox_min - margin, bbox_max + margin
    if np.any(p < lo) or np.any(p > hi):
        raise ValueError(
            f"trace_panorama: position {p.tolist()} lies outside the scene's bounding box "
            f"[{bbox_min.tolist()}, {bbox_max.tolist()}] expanded by {BBOX_MARGIN:.0%} of its "
            f"diagonal (= [{lo.tolist()}, {hi.tolist()}])")
    return p


def _excluding_scene(shapes, position: np.ndarray, radius: float):
    """(scene of the surfels farther than ``radius`` from ``position``, {shape id: excluded})."""
    d = {"type": "scene"}
    excluded = {}
    for k, sh in enumerate(shapes):
        means = np.asarray(dr.detach(sh.params.means), np.float64).T              # [N, 3]
        near = np.linalg.norm(means - position, axis=1) <= radius                 # NaN -> kept
        sid = sh.id() or f"surfels_{k}"
        if sid in excluded:
            sid = f"{sid}_{k}"
        excluded[sid] = int(near.sum())
        if near.all():
            continue                                    # the whole shape is left out
        sub = sh.params.subset(~near) if near.any() else sh.params
        d[sid] = SurfelShapeBase.from_params(sub, id=sid)
    if len(d) == 1:
        total = sum(excluded.values())
        raise ValueError(
            f"trace_panorama: exclude_radius={radius} around {position.tolist()} leaves out all "
            f"{total} surfels of the scene; use a smaller radius")
    return mi.load_dict(d), excluded


# ---------------------------------------------------------------------------------------
# Tracing

MAX_PASSES = 16      # passes of max_hits per ray: every surfel composited, as step 1 trains

def _trace_chunk(scene, shapes, eps, origin, dirs, max_hits, colour_space):
    """Premultiplied per-ray buffers as numpy: W [R], C [R,3], L [R,3], D [R], N [R,3]."""
    o = mi.Point3f(*[dr.full(mi.Float, float(c), len(dirs)) for c in origin])
    d = to_jit(mi.Vector3f, dirs.T)
    with dr.suspend_grad():
        _, out, _, _ = trace_composite(scene, shapes, mi.Ray3f(o, d), max_hits, eps,
                                       ("color", "weight", "depth", "normal"),
                                       max_passes=MAX_PASSES, keep_hits=False)
        W, C = out["weight"], out["color"]
        L = (colorspace.unpremultiplied_to_linear(C, W, W_EPS) if colour_space == "srgb"
             else mi.Color3f(dr.maximum(C, 0.0)))
        dr.eval(L)
    return (np.asarray(W), np.asarray(C).T, np.asarray(L).T, np.asarray(out["depth"]),
            np.asarray(out["normal"]).T)


def trace_panorama(scene, position, cfg: PanoramaConfig | None = None,
                   chunk: int = 1 << 19) -> dict:
    """Equirect panorama of the surfel ``scene`` (surfel shapes only) seen from ``position``.

    Returns numpy float32 arrays ``rgb`` [H, W, 3] (linear radiance, un-premultiplied),
    ``ldr`` [H, W, 3] (the radiance field's own display values, un-premultiplied),
    ``alpha`` [H, W] (coverage W), ``normal`` [H, W, 3] (unit world normals of the
    surfels, facing the position; 0 where uncovered), ``depth`` [H, W] (unbiased
    distance D/W, 0 where uncovered) and ``meta`` (dict: position, convention, sizes,
    coverage, excluded surfel counts, bbox, ...). Pixels with W < ``W_EPS`` are uncovered.

    Raises ValueError for a bad position (not 3 finite values, or outside the scene's bbox
    expanded by 10 % of its diagonal) or when ``exclude_radius`` removes every surfel. A
    panorama without coverage is returned with ``meta['coverage'] == 0.0`` and a warning.
    ``chunk``: rays traced per kernel launch (memory ∝ chunk · max_hits).
    """
    cfg = PanoramaConfig() if cfg is None else cfg
    cfg.validate()
    shapes = composite.surfel_shapes(scene, "trace_panorama")
    ensure_proxies(scene, shapes)
    bb = scene.bbox()
    bmin = np.array([bb.min[k] for k in range(3)], np.float64)
    bmax = np.array([bb.max[k] for k in range(3)], np.float64)
    pos = _check_position(position, bmin, bmax)

    excluded = {}
    if cfg.exclude_radius > 0:
        scene, excluded = _excluding_scene(shapes, pos, float(cfg.exclude_radius))
        shapes = composite.surfel_shapes(scene, "trace_panorama")
    eps = composite.auto_epsilon(scene, shapes)

    Wd, H, s = int(cfg.width), int(cfg.height), int(cfg.supersample)
    ss = s * s
    npix = Wd * H
    acc_w = np.empty(npix, np.float64)
    acc_c = np.empty((npix, 3), np.float64)
    acc_l = np.empty((npix, 3), np.float64)
    acc_d = np.empty(npix, np.float64)
    acc_n = np.empty((npix, 3), np.float64)
    rng = np.random.default_rng(cfg.seed)
    step = max(1, int(chunk) // ss)                                     # pixels per launch
    for a in range(0, npix, step):
        b = min(npix, a + step)
        dirs = pixel_directions(Wd, H, a, b, s, rng).astype(np.float32)
        w, c, l, d, n = _trace_chunk(scene, shapes, eps, pos, dirs, int(cfg.max_hits),
                                     cfg.colour_space)
        m = b - a
        acc_w[a:b] = w.reshape(m, ss).mean(1)
        acc_c[a:b] = c.reshape(m, ss, 3).mean(1)
        acc_l[a:b] = l.reshape(m, ss, 3).mean(1)
        acc_d[a:b] = d.reshape(m, ss).mean(1)
        acc_n[a:b] = n.reshape(m, ss, 3).mean(1)

    covered = acc_w >= W_EPS
    inv = np.where(covered, 1.0 / np.maximum(acc_w, W_EPS), 0.0)
    ldr = acc_c * inv[:, None]
    rgb = acc_l * inv[:, None]
    depth = acc_d * inv
    nlen = np.linalg.norm(acc_n, axis=1)
    normal = np.where((covered & (nlen > 1e-12))[:, None],
                      acc_n / np.maximum(nlen, 1e-12)[:, None], 0.0)
    alpha = acc_w.reshape(H, Wd)
    cov = coverage(alpha)
    if cov <= 0.0:
        cov = 0.0
        log.warning("trace_panorama: nothing covers the panorama from %s (%d surfels traced, "
                    "%d excluded); the result is empty", pos.tolist(),
                    sum(sh.params.count for sh in shapes), sum(excluded.values()))
    meta = {
        "position": pos.tolist(), "convention": CONVENTION, "width": Wd, "height": H,
        "supersample": s, "max_hits": int(cfg.max_hits), "colour_space": cfg.colour_space,
        "exclude_radius": float(cfg.exclude_radius),
        "excluded": int(sum(excluded.values())), "excluded_per_shape": excluded,
        "surfels": int(sum(sh.params.count for sh in shapes)), "coverage": cov,
        "bbox": [bmin.tolist(), bmax.tolist()],
    }
    f32 = np.float32
    return {"rgb": rgb.reshape(H, Wd, 3).astype(f32), "ldr": ldr.reshape(H, Wd, 3).astype(f32),
            "alpha": alpha.astype(f32), "normal": normal.reshape(H, Wd, 3).astype(f32),
            "depth": depth.reshape(H, Wd).astype(f32), "meta": meta}


def composite_background(trace: dict, radiance: np.ndarray, observed: np.ndarray,
                         clipped: np.ndarray | None = None) -> dict:
    """A :func:`trace_panorama` result with a far-field background behind the surfels.

    ``radiance`` [H, W, 3]: the background in the radiance field's own colour space
    (step 1's learned environment, looked up at the panorama's pixels); ``observed``
    [H, W] in [0, 1]: how much of it the capture saw (``comgs_dr.train.background``).
    Where the surfels leave transmittance T = 1 − W, the background adds T·observed of
    coverage: alpha' = W + T·o, colours are the coverage-weighted mix, normals of the
    background face the position (−d), the depth stays the surfels'. Directions from the
    position are the capture's directions: the background is at infinity.
    ``background_alpha`` [H, W]: the background's share T·o of each pixel (open sky, where
    ``alpha`` also counts the surfels).
    """
    H, Wd = trace["alpha"].shape
    if radiance.shape != (H, Wd, 3) or observed.shape != (H, Wd):
        raise ValueError(f"composite_background: background {radiance.shape} / observed "
                         f"{observed.shape} do not match the panorama {(H, Wd)}")
    W = np.clip(trace["alpha"].astype(np.float64), 0.0, 1.0)                     # [H, W]
    o = np.clip(observed, 0.0, 1.0) * (1.0 - W)                                  # [H, W]
    a = W + o
    inv = np.where(a >= W_EPS, 1.0 / np.maximum(a, W_EPS), 0.0)[..., None]
    srgb = trace["meta"].get("colour_space", "srgb") == "srgb"
    env = np.maximum(np.asarray(radiance, np.float64), 0.0)
    if clipped is not None:
        if np.shape(clipped) != (H, Wd, 3):
            raise ValueError(f"composite_background: clipped {np.shape(clipped)} does not "
                             f"match the panorama {(H, Wd, 3)}")
        env = np.where(np.asarray(clipped) >= 0.5, np.maximum(env, 1.0), env)
    env_lin = np.asarray(colorspace.srgb_decode(np.clip(env, 0.0, 1.0))) if srgb else env
    out = dict(trace)
    out["ldr"] = ((W[..., None] * trace["ldr"] + o[..., None] * env) * inv).astype(np.float32)
    out["rgb"] = ((W[..., None] * trace["rgb"] + o[..., None] * env_lin) * inv).astype(np.float32)
    n = W[..., None] * trace["normal"] - o[..., None] * equirect_directions(H, Wd)
    nlen = np.linalg.norm(n, axis=-1, keepdims=True)
    out["normal"] = np.where(nlen > 1e-12, n / np.maximum(nlen, 1e-12), 0.0).astype(np.float32)
    out["alpha"] = a.astype(np.float32)
    out["background_alpha"] = o.astype(np.float32)
    meta = dict(trace["meta"])
    meta["coverage_surfels"] = meta.get("coverage")
    meta["coverage"] = coverage(a)
    meta["background"] = True
    out["meta"] = meta
    return out
