"""The sun from the scene's own cast shadows (beyond the paper).

A panorama method only finds the lights its capture looked at, and outdoor captures rarely
look at the sun; they nearly always see the shadows it casts. With the scene's surfels and
their step-1 radiance, this module finds the distant sun (direction d, its irradiance
relative to the sky's) that explains where the scene is darker than its surroundings.

Model (Lambertian receivers: grounds, floors and the tops of blocks facing up, within
``MAX_TILT_DEG`` of +z after a plane fit to the surfels around them, and walls, within
``WALL_RECV_DEG`` of horizontal): a receiver x of albedo ρ(x) has radiance

    L(x) = ρ(x)/π · E_sky(x) · (1 + k V_d(x) (n·d)⁺),      k = E_sun(facing d) / E_sky,

with V_d the transmittance from x toward d through the scene's own surfels (traced); the
sky term is divided out first (L / a(x), a the traced, cosine-weighted fraction of the sky x
sees: the foot of a wall is dark under any sun). The
albedo is unknown but, on a textured surface, independent of where shadows fall. For a
candidate d, each receiver V_d puts in shadow is compared with the median of the lit
receivers on its plane within ``radius_frac`` × the receivers' extent: c(x) = log(median
lit L / L(x)). The true sun makes these darkenings consistently positive; a wrong one picks
receivers at random. The direction maximises the z-score mean(c) / standard error, the
grounds' and the walls' summed (a shadow that ends on a wall leaves a ridge of elevations on
the ground; its height on the wall fixes the elevation: ``test_sun_fit``, the composition
benchmark 10.4° → 5.2° off), over a Fibonacci grid of the upper hemisphere refined around
the best; k per channel follows from the median darkening of the ground's receivers in the
shadow's core (``CORE_DEG``: an edge blurred by step 1 reads half a shadow),
log(1 + k cos) = median c (medians: robust to texture and to the traced shadow's edge, a
surfel wider than the true one).

Usable or not (``SunFit.usable`` and ``reason``): the best z must reach ``MIN_Z`` and
``RIVAL_RATIO`` × the best z of the directions whose shadows share less than ``RIVAL_OVERLAP``
of the smaller one with its own (another explanation of the darkening, not the same shadow
stretched or moved), each counted without the best shadow's receivers (``_Fitter.rival``),
and its
shadow cover between ``MIN_SHADOWED`` and ``MAX_SHADOWED`` of the receivers. A scene with no
cast shadow (overcast, indoor without a dominant light) or no shadow caster in view gives
no usable fit, and nothing is added to the light.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import mitsuba as mi
import numpy as np
from scipy.spatial import cKDTree

from comgs_dr.core.colorspace import srgb_decode
from comgs_dr.core.equirect import equirect_directions, resize_mask, solid_angle_image
from comgs_dr.core.hostarray import to_jit
from comgs_dr.lighting import clear_sky
from comgs_dr.sops.occlusion import plane_normals
from comgs_dr.surfels.io import quat_to_matrix
from comgs_dr.surfels.params import base_colour
from comgs_dr.surfels.trace import trace_visibility

log = logging.getLogger(__name__)

MAX_TILT_DEG = 25.0       # receivers: normals within this of +z
MIN_Z = 6.0               # z-score of the best sun's darkening of its shadowed receivers
RIVAL_OVERLAP = 0.3       # ... and RIVAL_RATIO × that of the best direction whose shadow
RIVAL_RATIO = 1.5         # shares less than this of the smaller of the two (``_overlap``)
MIN_SHADOWED = 0.005      # of the receivers in the best sun's shadow (V < 0.5)
MAX_SHADOWED = 0.8
PLATEAU = 0.85            # directions within this fraction of the best z: one ridge
MIN_SKY = 0.05            # sky visibility floor of the receivers' radiance correction
WALL_TILT_DEG = 80.0      # surfels whose own normal is this far from vertical: walls
WALL_RECV_DEG = 20.0      # wall receivers: fitted and own normals within this of horizontal
SAME_PLANE_DEG = 30.0     # a receiver's lit neighbours face within this of its own normal
PLANE_GAP = 0.25          # ... and lie within this × their radius of its plane
CORE_DEG = 3.0            # k is read where the shadow holds toward every direction this close
OFFSET_SCALES = 3.0       # shadow rays start this many median surfel scales above x
HOT_FACTOR = 4.0          # unobserved sky this much above its median: a guessed light
LUMA = np.array([0.2126, 0.7152, 0.0722])


@dataclasses.dataclass
class SunFitConfig:
    """``points``: receivers sampled; lit neighbours within ``radius_frac`` × the
    receivers' extent are a shadowed receiver's reference; ``directions``: the coarse grid
    over the upper hemisphere (above ``min_elevation_deg``), then ``refine`` directions
    drawn around the best ``refine_top`` (Gaussian, 0.75 coarse spacings); ``max_hits``:
    surfels per traced pass."""
    points: int = 6000
    radius_frac: float = 0.05
    directions: int = 256
    refine: int = 48
    refine_top: int = 3
    min_elevation_deg: float = 3.0
    max_hits: int = 16
    seed: int = 0

    def validate(self):
        for f in ("points", "directions", "max_hits"):
            if int(getattr(self, f)) < 1:
                raise ValueError(f"SunFitConfig: {f} must be ≥ 1, got {getattr(self, f)!r}")
        if not 0 < self.radius_frac <= 1:
            raise ValueError(f"SunFitConfig: radius_frac must be in (0, 1], got {self.radius_frac}")
        if not 0 <= self.min_elevation_deg < 90:
            raise ValueError(f"SunFitConfig: min_elevation_deg must be in [0, 90), got "
                             f"{self.min_elevation_deg}")


@dataclasses.dataclass
class SunFit:
    """``direction`` [3] world unit vector toward the sun; ``k``: E_sun(facing d)/E_sky(up)
    (luminance); ``k_rgb`` [3] per channel at ``direction``; ``z``: the z-score of its
    shadow's darkening; ``rival``: the best z of the other shadows (``RIVAL_OVERLAP``);
    ``shadowed``: fraction of receivers in its shadow; ``usable`` and ``reason``; ``receivers``; ``seconds``."""
    direction: np.ndarray
    k: float
    k_rgb: np.ndarray
    z: float
    rival: float
    shadowed: float
    usable: bool
    reason: str
    receivers: int
    seconds: float

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["direction"] = [float(v) for v in self.direction]
        d["k_rgb"] = [float(v) for v in self.k_rgb]
        return d


def fibonacci_hemisphere(n: int, min_elevation_deg: float = 0.0) -> np.ndarray:
    """[n, 3] near-uniform unit directions with z ≥ sin(min elevation)."""
    z0 = np.sin(np.radians(min_elevation_deg))
    i = np.arange(n) + 0.5
    z = 1.0 - (1.0 - z0) * i / n
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.c_[r * np.cos(phi), r * np.sin(phi), z]


def receivers(means, normals, colour_lin, opacity, cfg: SunFitConfig, own_normals=None):
    """(x [M, 3], n [M, 3], L [M, 3] linear) of opaque, lit surfels: grounds (``normals``
    within ``MAX_TILT_DEG`` of +z, flipped to +z) and walls (within ``WALL_RECV_DEG`` of
    horizontal, their ``own_normals`` too; each taken with both signs of its normal, as a
    surfel's sign is arbitrary: the copy facing into the wall traces into it and finds no
    lit neighbour). A shadow that ends on a wall fixes only the sun's azimuth on the
    ground; its height on the wall fixes the elevation."""
    n = np.asarray(normals, np.float64)
    n = n * np.where(n[:, 2:3] < 0, -1.0, 1.0)
    own = n if own_normals is None else np.asarray(own_normals, np.float64)
    lum = colour_lin @ LUMA
    ok = (opacity >= 0.5) & (lum > 1e-4) & np.isfinite(means).all(1) \
        & np.isfinite(colour_lin).all(1)
    ground = ok & (n[:, 2] >= np.cos(np.radians(MAX_TILT_DEG))) \
        & (np.abs(own[:, 2]) >= np.cos(np.radians(WALL_TILT_DEG)))
    flat = np.sin(np.radians(WALL_RECV_DEG))
    wall = ok & (n[:, 2] <= flat) & (np.abs(own[:, 2]) <= flat) if own_normals is not None \
        else np.zeros(len(n), bool)
    idx = np.flatnonzero(ground | wall)
    if len(idx) > cfg.points:
        idx = np.random.default_rng(cfg.seed).choice(idx, cfg.points, replace=False)
    w = idx[wall[idx]]
    x = np.concatenate([means[idx], means[w]]).astype(np.float64)
    nn = np.concatenate([n[idx], -n[w]])
    return x, nn, np.concatenate([colour_lin[idx], colour_lin[w]]).astype(np.float64)


class _Fitter:
    """Shadow evidence per sun direction for one set of receivers (``visibility(d) -> V``)."""

    def __init__(self, x, n, L, visibility, cfg: SunFitConfig):
        self.n, self.visibility = n, visibility
        self.extent = float(np.linalg.norm(np.ptp(x, 0)))
        self.logL = np.log(np.maximum(L, 1e-6))                               # [M, 3]
        self.lum = np.log(np.maximum(L @ LUMA, 1e-6))
        self.nbrs = _same_plane_neighbours(x, n, cfg.radius_frac * self.extent)
        self.ground = n[:, 2] >= np.cos(np.radians(MAX_TILT_DEG))
        self.cache = {}

    def contrasts(self, V, cos, per_channel: bool = False, ground_only: bool = False,
                  with_kind: bool = False):
        """[S, C] log(median lit neighbours / receiver) of each receiver in the shadow
        (V < 0.5) with ≥ 3 lit ones (V > 0.5) on its plane (``_same_plane_neighbours``),
        and their cos to the sun; ``ground_only``: of the up-facing receivers only;
        ``with_kind``: also [S] bool, up-facing or not."""
        val = self.logL if per_channel else self.lum[:, None]
        dark = np.flatnonzero((V < 0.5) & (cos > 0.05) & (self.ground | (not ground_only)))
        lit = (V > 0.5) & (cos > 0.05)
        out, cs, kind = [], [], []
        for i in dark:
            j = self.nbrs[i][lit[self.nbrs[i]]]
            if len(j) >= 3:
                out.append(np.median(val[j], 0) - val[i])
                cs.append(np.median(cos[j]))
                kind.append(self.ground[i])
        res = (np.array(out).reshape(-1, val.shape[1]), np.array(cs))
        return res + (np.array(kind, bool),) if with_kind else res

    def score(self, d):
        """(z, V): the z-scores of the shadowed receivers' darkening against their lit
        neighbours (mean / standard error; 0 with fewer than 5), the grounds' and the walls'
        summed (Stouffer's combination of independent evidence, up to √2: a few wall
        receivers a shadow climbs tell the sun's elevation that a ground shadow ending on the
        wall cannot; counted together, the ground's many would drown them)."""
        key = tuple(np.round(d, 6))
        if key not in self.cache:
            V = self.visibility(d)
            c, _, on_ground = self.contrasts(V, self.n @ d, with_kind=True)
            z = sum(_z_score(c[on_ground == g, 0]) for g in (True, False))
            self.cache[key] = (z, V)
        return self.cache[key]

    def rival(self, z: float, V) -> float:
        """The best z of another explanation of the darkening than the shadow ``V`` of
        z-score ``z``: over the scored directions whose shadows share less than
        ``RIVAL_OVERLAP`` with ``V``, each scored without the receivers in ``V``'s shadow
        (neither dark nor lit for it). A grazing direction whose long shadow takes in part
        of the true one borrows that shadow's darkening; counted without it, it must
        darken receivers of its own (the demo's scene: a 4° direction shading 48 % of the
        ground, z 7.8 with the true shadow's receivers, against the true sun's 10.7)."""
        floor = 0.5 * z / RIVAL_RATIO            # rivals far below cannot decide the test
        own = V < 0.5
        best = 0.0
        for key, (zr, Vr) in self.cache.items():
            if zr < floor or _overlap(Vr < 0.5, own) >= RIVAL_OVERLAP:
                continue
            c, _, on_ground = self.contrasts(np.where(own, 0.5, Vr), self.n @ np.array(key),
                                             with_kind=True)
            best = max(best, sum(_z_score(c[on_ground == g, 0]) for g in (True, False)))
        return best

    def k_rgb(self, d, V):
        """k per channel from the median contrast of the up-facing receivers in the shadow's
        core (:meth:`core`): log(1 + k cos) = median log ratio (a wall sees less sky than
        the ground: its k is not E_up's)."""
        Vc = self.core(d, V)
        c, cs = self.contrasts(Vc, self.n @ d, per_channel=True, ground_only=True)
        if len(c) < 5:
            return np.zeros(3)
        return np.maximum(np.expm1(np.median(c, 0)), 0.0) / max(float(np.median(cs)), 1e-3)

    def core(self, d, V):
        """``V`` with the shadow's edge set to 0.5 (neither shadowed nor lit): receivers stay
        shadowed (lit) only when they are so toward every direction within ``CORE_DEG`` of
        d. Step 1 blurs a shadow's edge and the traced shadow of wide surfels is not the true
        one: edge receivers read half a shadow and the median contrast, k, comes out low
        (the demo's scene: k 0.72× the truth's from every shadowed receiver, 1.0× from the
        core; docs/composite.md)."""
        t1 = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(d, t1)
        r = np.radians(CORE_DEG)
        Vs = [V] + [self.visibility(np.cos(r) * d + np.sin(r) * (np.cos(a) * t1 + np.sin(a) * t2))
                    for a in np.linspace(0.0, 2 * np.pi, 6, endpoint=False)]
        dark, lit = np.maximum.reduce(Vs) < 0.5, np.minimum.reduce(Vs) > 0.5
        return np.where(dark, 0.0, np.where(lit, 1.0, 0.5))


def _z_score(c: np.ndarray) -> float:
    """mean / standard error of the log darkenings ``c`` [S]; 0 with fewer than 5."""
    if len(c) < 5:
        return 0.0
    return float(c.mean() / (c.std() / np.sqrt(len(c)) + 1e-9))


def _same_plane_neighbours(x, n, radius: float) -> list:
    """Per receiver, the receivers within ``radius`` on its plane: facing within
    ``SAME_PLANE_DEG`` of its normal and ≤ ``PLANE_GAP`` × radius off its plane (a block's top
    is not the ground around it; a wall's inward copy is not its other face's outward one)."""
    cos_same = np.cos(np.radians(SAME_PLANE_DEG))
    out = []
    for i, js in enumerate(cKDTree(x).query_ball_point(x, radius)):
        js = np.asarray(js, int)
        keep = (n[js] @ n[i] >= cos_same) & (np.abs((x[js] - x[i]) @ n[i]) <= PLANE_GAP * radius)
        out.append(js[keep])
    return out


def fit_sun(x, n, L, visibility, cfg: SunFitConfig | None = None, progress=None,
            direction=None) -> SunFit:
    """The sun explaining the receivers' shadows (module docstring). ``x``/``n``/``L``:
    [M, 3] receiver positions, up-facing normals and linear radiance; ``visibility(d)``:
    [M] transmittance toward unit ``d`` (e.g. :func:`traced_visibility`).

    ``direction``: a sun direction known otherwise (the panorama saw the sun, clipped):
    no search, only k per channel is read from the shadows toward it; usable when its
    shadow darkens the receivers with z ≥ ``MIN_Z`` and covers the usual share (there is
    no rival test: the direction is not chosen by the shadows)."""
    cfg = cfg or SunFitConfig()
    cfg.validate()
    t0 = time.perf_counter()
    if len(x) < 50:
        return SunFit(np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(3), 0.0, 0.0, 0.0, False,
                      f"only {len(x)} up-facing receivers (ground, floor): nothing to read "
                      f"shadows on", len(x), time.perf_counter() - t0)
    f = _Fitter(x, n, L, visibility, cfg)
    if direction is not None:
        return _fit_at(f, np.asarray(direction, np.float64), len(x), t0)
    coarse = fibonacci_hemisphere(cfg.directions, cfg.min_elevation_deg)
    scores = []
    for d in coarse:
        scores.append(f.score(d)[0])
        if progress is not None:
            progress(1)
    spacing = np.sqrt(2 * np.pi / cfg.directions)                              # rad
    rng = np.random.default_rng(cfg.seed)
    for b in coarse[np.argsort(scores)[::-1][:cfg.refine_top]]:
        for _ in range(cfg.refine // max(cfg.refine_top, 1)):
            d = b + rng.normal(size=3) * spacing * 0.75
            d[2] = max(d[2], np.sin(np.radians(cfg.min_elevation_deg)))
            f.score(d / np.linalg.norm(d))
            if progress is not None:
                progress(1)
    d = _plateau_direction(f.cache)
    z, V = f.score(d)
    shadowed = float(np.mean((V < 0.5) & (f.n @ d > 0)))
    rival = f.rival(z, V)
    if z < MIN_Z or z < RIVAL_RATIO * max(rival, 0.0):
        usable, reason = False, (f"no usable cast shadow: the best sun darkens its shadowed "
                                 f"receivers with z = {z:.1f}, the best other shadow "
                                 f"z = {rival:.1f} (needs ≥ {MIN_Z:g} and {RIVAL_RATIO:g}× "
                                 f"the rival)")
    elif not MIN_SHADOWED <= shadowed <= MAX_SHADOWED:
        usable, reason = False, (f"the best sun shades {100 * shadowed:.1f}% of the "
                                 f"receivers (needs {100 * MIN_SHADOWED:.1f}–"
                                 f"{100 * MAX_SHADOWED:.0f}%)")
    else:
        usable, reason = True, (f"its shadow darkens the receivers with z = {z:.1f} "
                                f"(the best other shadow: {rival:.1f}) and covers "
                                f"{100 * shadowed:.1f}% of them")
    k_rgb = f.k_rgb(d, V)
    return SunFit(d, float(k_rgb @ LUMA), k_rgb, z, rival, shadowed, usable, reason, len(x),
                  time.perf_counter() - t0)


def _fit_at(f: _Fitter, d: np.ndarray, receivers_: int, t0: float) -> SunFit:
    """k per channel toward a given direction ``d`` and whether its shadow is evidence."""
    d = d / np.linalg.norm(d)
    z, V = f.score(d)
    shadowed = float(np.mean((V < 0.5) & (f.n @ d > 0)))
    if z < MIN_Z:
        usable, reason = False, (f"the shadows toward the seen sun darken the receivers with "
                                 f"z = {z:.1f} (needs ≥ {MIN_Z:g})")
    elif not MIN_SHADOWED <= shadowed <= MAX_SHADOWED:
        usable, reason = False, (f"the seen sun shades {100 * shadowed:.1f}% of the "
                                 f"receivers (needs {100 * MIN_SHADOWED:.1f}–"
                                 f"{100 * MAX_SHADOWED:.0f}%)")
    else:
        usable, reason = True, (f"the shadows toward the seen sun darken the receivers with "
                                f"z = {z:.1f} and cover {100 * shadowed:.1f}% of them")
    k_rgb = f.k_rgb(d, V)
    return SunFit(d, float(k_rgb @ LUMA), k_rgb, z, 0.0, shadowed, usable, reason, receivers_,
                  time.perf_counter() - t0)


def _plateau_direction(cache: dict) -> np.ndarray:
    """The z-weighted mean of the directions within ``PLATEAU`` of the best z. A shadow that
    ends on a wall or beyond the receivers fixes the sun's azimuth but leaves a ridge of
    elevations nearly as good, whose noisy maximum can lie far from the true elevation; the
    ridge's weighted mean is the better estimate."""
    q = np.array([np.array(k) / np.linalg.norm(k) for k in cache])
    z = np.array([v[0] for v in cache.values()])
    w = np.maximum(z - PLATEAU * z.max(), 0.0)
    if w.sum() <= 0:
        return q[int(np.argmax(z))]
    d = (w[:, None] * q).sum(0)
    return d / np.linalg.norm(d)


def _overlap(a: np.ndarray, b: np.ndarray) -> float:
    """|a ∩ b| / min(|a|, |b|): 1 when one shadow holds the other (a longer shadow of the
    same caster toward a lower sun), 0 for disjoint ones."""
    small = min(np.count_nonzero(a), np.count_nonzero(b))
    return np.count_nonzero(a & b) / small if small else 0.0


def traced_visibility(scene, x, n, offset: float, max_hits: int = 16):
    """``visibility(d)`` for :func:`fit_sun`: transmittance from ``x + offset n`` toward d
    through the surfels of ``scene`` (``surfels.trace``: every surfel composited)."""
    org = to_jit(mi.Point3f, (x + offset * n).astype(np.float32).T)
    m = len(x)

    def vis(d):
        w = to_jit(mi.Vector3f, np.tile(np.asarray(d, np.float32), (m, 1)).T)
        occ, _ = trace_visibility(scene, org, w, max_hits, radiance=False)
        return 1.0 - np.clip(np.asarray(occ, np.float64), 0.0, 1.0)
    return vis


# ----------------------------------------------------------------------------- fusion

def up_irradiance(radiance_eq: np.ndarray) -> np.ndarray:
    """[3] irradiance of an equirect map on a surface facing +z."""
    h, w = radiance_eq.shape[:2]
    cos = np.maximum(equirect_directions(h, w)[..., 2], 0.0)
    return np.einsum("hwc,hw->c", radiance_eq, cos * solid_angle_image(h, w))


def add_sun(radiance_eq: np.ndarray, observed: np.ndarray, fit: SunFit,
            radius_deg: float = 1.0, replace_deg: float = 25.0,
            unseen_sky: str = "clear", turbidity: float | None = None,
            max_ground_albedo: float = clear_sky.MAX_GROUND_ALBEDO):
    """The panorama with the fitted sun: (new equirect [H, W, 3], what was done: str).

    The panorama keeps what it saw: if the sun's direction was observed (``observed``
    [H, W] bool, the traced panorama's mask), nothing changes. Otherwise the completion's
    guess there is replaced: unobserved pixels within ``replace_deg`` of the sun brighter
    than the unobserved sky's median are set to that median (a guessed sun elsewhere in
    the cone would double it), as are unobserved pixels anywhere above the horizon brighter
    than ``HOT_FACTOR`` × that median (a completion's guessed sun far from the one the shadows
    show would cast a second shadow). ``unseen_sky`` "clear" (default): the unobserved sky
    then takes a clear sky's shape and colour for this sun at its own luminance
    (``clear_sky.fill_unseen_sky``: the completion guesses the sky from the ground's colour),
    of ``turbidity`` (None: the one whose sun/sky ratio is the fit's k,
    ``clear_sky.turbidity_for``); "completion": it stays the completion's. Then the unseen
    sky is raised if its level makes the ground reflect more than ``max_ground_albedo`` of
    what it receives (``clear_sky.ground_albedo_floor``; 0: off). Last a disk of
    ``radius_deg`` is added whose irradiance on a surface facing it is k_rgb × the map's
    E(up)."""
    rad = np.array(radiance_eq, np.float64)
    h, w = rad.shape[:2]
    observed = resize_mask(observed, h, w)
    dirs = equirect_directions(h, w)
    cosd = dirs @ fit.direction
    disk = cosd >= np.cos(np.radians(max(radius_deg, 1e-3)))
    near = cosd >= np.cos(np.radians(3 * max(radius_deg, 1.0)))
    if observed[near].mean() > 0.5:
        return radiance_eq, "kept: the panorama observed the sun's direction"
    unseen = ~observed & (dirs[..., 2] > 0)
    sky = np.median(rad[unseen], 0) if unseen.any() else np.zeros(3)
    lum, ref = rad @ LUMA, float(sky @ LUMA)
    cone = (cosd >= np.cos(np.radians(replace_deg))) & unseen
    hot = (cone & (lum > ref)) | (unseen & (lum > HOT_FACTOR * ref))
    rad[hot] = sky
    sky_note = ""
    if unseen_sky == "clear":
        if turbidity is None:
            turbidity = clear_sky.turbidity_for(fit.direction, fit.k)
        rad, scale = clear_sky.fill_unseen_sky(rad, unseen, fit.direction, turbidity)
        sky_note = (f", the unseen sky a clear sky (turbidity {turbidity:.1f}) at the "
                    f"completion's luminance" if scale > 0 else "")
    elif unseen_sky != "completion":
        raise ValueError(f"add_sun: unseen_sky must be 'clear' or 'completion', got "
                         f"{unseen_sky!r}")
    rad, lift, implied = clear_sky.ground_albedo_floor(
        rad, unseen, fit.k_rgb, float(np.arcsin(np.clip(fit.direction[2], -1, 1))),
        max_ground_albedo)
    if lift > 1.0:
        sky_note += (f", raised {lift:.2f}x (the ground reflected "
                     f"{', '.join(f'{a:.2f}' for a in implied)} of its light"
                     + (", the most it is raised)" if lift >= clear_sky.MAX_LIFT else ")"))
    e_up = up_irradiance(rad)                        # the sky's, without a (guessed) sun
    if not disk.any():                  # a disk smaller than a pixel: the nearest pixel
        disk = np.zeros((h, w), bool)
        disk.flat[int(np.argmax(cosd))] = True
    omega = float(solid_angle_image(h, w)[disk].sum())
    L = np.asarray(fit.k_rgb) * e_up / max(omega, 1e-12)
    rad[disk] += L
    return rad.astype(np.float32), (f"added: a sun of {radius_deg:.1f}° at elevation "
                                    f"{np.degrees(np.arcsin(fit.direction[2])):.1f}°, "
                                    f"E_sun/E_up {fit.k:.2f} (k), {int(hot.sum())} guessed "
                                    f"hot pixels of the unobserved sky reset{sky_note}")


def seen_sun(radiance_eq: np.ndarray, observed: np.ndarray, near: np.ndarray,
             cone_deg: float = 30.0):
    """The direction of the sun the panorama saw near ``near`` (a fitted direction), or None.

    Among the observed pixels within ``cone_deg`` of ``near``, those brighter than
    ``HOT_FACTOR`` × the observed sky's median luminance are the sun; its direction is
    their luminance-weighted mean. The fit's own direction can sit on a ridge of
    elevations (a shadow that ends on a wall); a sun in view fixes it."""
    rad = np.asarray(radiance_eq, np.float64)
    h, w = rad.shape[:2]
    observed = resize_mask(observed, h, w)
    dirs = equirect_directions(h, w)
    sky = observed & (dirs[..., 2] > 0)
    if not sky.any():
        return None
    lum = rad @ LUMA
    ref = float(np.median(lum[sky]))
    hot = sky & (dirs @ np.asarray(near) >= np.cos(np.radians(cone_deg))) & (
        lum > HOT_FACTOR * max(ref, 1e-12))
    if not hot.any():
        return None
    wgt = (lum * solid_angle_image(h, w))[hot]
    d = (wgt[:, None] * dirs[hot]).sum(0)
    return d / np.linalg.norm(d)


def rescale_seen_sun(radiance_eq: np.ndarray, fit: SunFit, radius_deg: float = 8.0,
                     ring_deg: float = 12.0):
    """The panorama with its seen sun's irradiance set from the shadows: (new equirect
    [H, W, 3], what was done: str).

    A sun in a photo clips: the panorama knows where it is but guesses its power and
    colour (from the clipped pixels' surroundings, bluish under a blue sky). The shadows
    measure both, relative to the sky: k_rgb = E_sun(facing d) / E_up per channel
    (:func:`fit_sun` with ``direction``). The sun is the excess radiance within
    ``radius_deg`` of ``fit.direction`` above the median of the ring out to ``ring_deg``;
    it is scaled per channel so that its irradiance on a surface facing it is k_rgb × the
    E(up) of the rest of the map."""
    rad = np.array(radiance_eq, np.float64)
    h, w = rad.shape[:2]
    dirs = equirect_directions(h, w)
    sa = solid_angle_image(h, w)
    cosd = dirs @ fit.direction
    disk = cosd >= np.cos(np.radians(radius_deg))
    ring = (cosd >= np.cos(np.radians(ring_deg))) & ~disk
    if not disk.any() or not ring.any():
        return radiance_eq, "kept: the sun's disk is smaller than the map's pixels"
    bg = np.median(rad[ring], 0)
    excess = np.maximum(rad[disk] - bg, 0.0)
    e_sun = (excess * (np.maximum(cosd, 0.0) * sa)[disk][:, None]).sum(0)
    sky = rad.copy()
    sky[disk] = bg
    target = np.asarray(fit.k_rgb, np.float64) * up_irradiance(sky)
    if not (e_sun > 1e-12).all():
        return radiance_eq, "kept: no sun above the sky around it in some channel"
    gain = target / e_sun
    rad[disk] = bg + excess * gain
    return rad.astype(np.float32), (f"rescaled the seen sun to the shadows' E_sun/E_up "
                                    f"{fit.k:.2f} (k; gain per channel "
                                    f"{', '.join(f'{g:.2f}' for g in gain)})")


def fitted_normals(means, normals, opacity, neighbours: int = 8, radius_spacings: float = 3.0):
    """[N, 3] normals of planes fitted to the opaque surfels around each surfel
    (:func:`comgs_dr.sops.occlusion.plane_normals`, radius ``radius_spacings`` × the median
    distance to the ``neighbours``-th neighbour): the surfels' own orientations scatter, many
    steep ones even on flat ground."""
    ok = (opacity >= 0.5) & np.isfinite(means).all(1)
    if ok.sum() < 3:
        return normals
    pts = means[ok]
    kk = min(neighbours + 1, len(pts))
    spacing = float(np.median(cKDTree(pts).query(pts, k=kk)[0][:, -1]))
    out = np.array(normals, np.float64)
    out[ok] = plane_normals(pts, normals[ok], pts, radius_spacings * max(spacing, 1e-9),
                            max_points=64)
    return out


def fit_sun_in_scene(scene, params, colour_space: str = "srgb",
                     cfg: SunFitConfig | None = None, progress=None) -> SunFit:
    """:func:`fit_sun` on a surfel scene: ``scene`` (Mitsuba, surfels only, for the shadow
    rays) and its ``params`` (``SurfelParams``: positions, orientations, opacities, the
    SH DC colour as the receivers' radiance, in ``colour_space`` 'srgb' or 'linear')."""
    cfg = cfg or SunFitConfig()
    return fit_sun(*scene_receivers(scene, params, colour_space, cfg), cfg, progress)


def scene_receivers(scene, params, colour_space: str = "srgb",
                    cfg: SunFitConfig | None = None):
    """(x, n, L, visibility) of :func:`fit_sun` from a surfel scene (see
    :func:`fit_sun_in_scene`): the up-facing, sky-open receivers, their radiance with the
    sky's occlusion divided out, and their traced visibility toward any direction."""
    cfg = cfg or SunFitConfig()
    d = params.to_numpy()
    normals = quat_to_matrix(d["quats"])[:, :, 2]
    colour = np.clip(base_colour(d["sh"]), 0.0, None)
    if colour_space == "srgb":
        colour = np.asarray(srgb_decode(np.clip(colour, 0.0, 1.0)), np.float64)
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(d["opacity_logit"], np.float64).reshape(-1)))
    means = np.asarray(d["means"], np.float64)
    fitted = fitted_normals(means, normals, opacity)
    x, n, L = receivers(means, fitted, colour, opacity, cfg, own_normals=normals)
    # shadow rays start above the surfel layer: a reconstructed ground is bumpy and tilted
    # surfels a scale wide shade their neighbours toward a low sun
    offset = OFFSET_SCALES * float(np.median(np.exp(np.asarray(d["log_scales"])).max(1)))
    vis = traced_visibility(scene, x, n, offset, cfg.max_hits)
    if len(x):                            # receivers must see the sky above them: not the
        open_ = vis(np.array([0.0, 0.0, 1.0])) > 0.5      # underside of a ground or a table
        x, n, L = x[open_], n[open_], L[open_]
        vis = traced_visibility(scene, x, n, offset, cfg.max_hits)
        L = L / np.maximum(sky_visibility(vis, n), MIN_SKY)[:, None]
    return x, n, L, vis


def sky_visibility(vis, n, rays: int = 48) -> np.ndarray:
    """[M] cosine-weighted fraction of the sky each receiver sees (``rays`` directions over
    the upper hemisphere, traced): the foot of a wall is darker than the open ground under any
    sun (half its sky is blocked), a darkening a shadow must not be credited with."""
    dirs = fibonacci_hemisphere(rays, 1.0)
    w = np.maximum(n @ dirs.T, 0.0)                                             # [M, rays]
    seen = np.stack([vis(d) for d in dirs], 1)
    return (w * seen).sum(1) / np.maximum(w.sum(1), 1e-12)
