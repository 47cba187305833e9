"""The geometry of cutting an object out of a whole-capture surfel reconstruction.

A user photographs an object standing on something (a table, a bed, the floor), walking
around it. Four pieces, all NumPy/SciPy on surfel centres (or SfM points):

1. :func:`look_at_point` — the point closest, in least squares, to every camera's optical
   axis: where the photographer kept the object.
2. :func:`fit_support_plane` — RANSAC for the dominant plane near that point that lies
   below it with the cameras above it (and, when the cameras agree on an up direction, not
   tilted away from it), refined by a weighted least-squares fit of its inliers; its normal
   points toward the cameras.
3. :func:`grow_object` — what stands on the plane: the connected components (radius graph)
   of surfels higher than a thin *slab* above the plane that come near the look-at point
   (the *body*; fragments of a few surfels, floaters, are passed over), then the low
   surfels of the slab that lie under the body's footprint and touch it (the object's
   base). Low surfels outside the footprint are floor, carpet or bed
   sheet and stay behind even where they touch the object.
4. :func:`cut_measures` — how clean the cut is: the opacity-weighted share of kept surfels
   below the plane, inside the slab, and inside the slab *and* lying flat (facing along the
   plane normal: the signature of floor or sheet remnants).

Heights are signed distances to the plane, ``h(x) = n·x + offset`` (positive on the
cameras' side). Lengths passed in are absolute (the stage scales its fractions of the
scene size). Problems raise :class:`CutError` with ``where`` (a file) in the message.
"""
from __future__ import annotations

import dataclasses

import numpy as np

#: Surfels whose normal is within this angle of the plane normal count as lying flat.
FLAT_DEG = 30.0
#: Points scoring the RANSAC hypotheses at most (a random subset of the support ball).
_SCORE_POINTS = 20000
#: Hypotheses scored at once (memory: chunk × points floats).
_CHUNK = 64
#: Least-squares refinements of the best hypothesis.
_REFINE = 3
#: Below this spread of the camera axes (degrees) the look-at point is regularised.
_MIN_SPREAD_DEG = 5.0


class CutError(ValueError):
    """A cut that cannot be made; the message names the file and the problem."""


@dataclasses.dataclass(frozen=True)
class Plane:
    """The support plane ``n·x + offset = 0``; ``n`` (unit) points toward the cameras."""
    normal: np.ndarray
    offset: float
    inliers: int                # points within the tolerance inside the support ball
    inlier_share: float         # their (weighted) share of the ball's points
    tolerance: float            # inlier distance (scene units)
    cameras_above: float        # share of the cameras on the normal's side

    def height(self, x) -> np.ndarray:
        """[N] signed heights of points [N, 3] above the plane."""
        return np.asarray(x, np.float64) @ self.normal + self.offset

    def foot(self, x) -> np.ndarray:
        """The orthogonal projection of point(s) ``x`` onto the plane."""
        x = np.asarray(x, np.float64)
        return x - self.height(x)[..., None] * self.normal


# ----------------------------------------------------------------------------- look-at point

def look_at_point(centres, directions, points=None) -> tuple[np.ndarray, float]:
    """(point [3], spread in degrees): the least-squares point nearest the camera axes.

    Minimises Σ_i |(I − d_i d_iᵀ)(p − c_i)|² over cameras at ``centres`` [C, 3] looking
    along ``directions`` [C, 3]. ``spread`` is asin(√λ_min) of the mean projector
    (I − d dᵀ): about the angle between the most different axes. Below
    ``_MIN_SPREAD_DEG`` (a forward-facing capture: nearly parallel axes) the point along the
    mean axis is ill-posed; it is pulled toward the median depth of ``points`` [N, 3] in
    front of the cameras (or one unit ahead) along the weak direction only.
    """
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]            # [C, 3, 3]
    m = proj.mean(0)
    b = np.einsum("cij,cj->i", proj, c) / len(c)
    lam = np.linalg.eigvalsh(m)
    spread = float(np.degrees(np.arcsin(np.sqrt(np.clip(lam[0], 0.0, 1.0)))))
    floor = np.sin(np.radians(_MIN_SPREAD_DEG)) ** 2
    if lam[0] >= floor:
        return np.linalg.solve(m, b), spread
    mu = floor - lam[0]                                               # Tikhonov toward p0
    p0 = _ahead_point(c, d, points)
    return np.linalg.solve(m + mu * np.eye(3), b + mu * p0), spread


def _ahead_point(c: np.ndarray, d: np.ndarray, points) -> np.ndarray:
    """The mean camera centre moved along the mean axis to the points' median depth."""
    c0, d0 = c.mean(0), d.mean(0)
    d0 /= max(np.linalg.norm(d0), 1e-12)
    depth = 1.0
    if points is not None and len(points):
        t = (np.asarray(points, np.float64) - c0) @ d0
        if np.any(t > 0):
            depth = float(np.median(t[t > 0]))
    return c0 + depth * d0


def mean_up(ups) -> np.ndarray | None:
    """The cameras' common up direction (unit), or None when their up vectors disagree
    (mean length < 0.5: a capture turned on its side as often as upright)."""
    u = np.asarray(ups, np.float64).reshape(-1, 3)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    m = u.mean(0)
    n = float(np.linalg.norm(m))
    return m / n if n >= 0.5 else None


# ----------------------------------------------------------------------------- support plane

def fit_support_plane(points, weights, look_at, cameras, *, tolerance: float, radius: float,
                      iterations: int = 400, up=None, max_tilt_deg: float = 50.0,
                      min_inlier_share: float = 0.05, seed: int = 0,
                      where: str = "points") -> Plane:
    """The dominant plane within ``radius`` of ``look_at`` lying below it (see the module).

    points [N, 3], weights [N] (e.g. opacity; ≥ 0), cameras [C, 3] centres. A hypothesis
    (a plane through 3 weighted-random points of the ball) counts when the look-at point is
    more than ``tolerance`` above it, ≥ 80 % of the cameras are above it and, with ``up``,
    its normal is within ``max_tilt_deg`` of ``up``; its score is the weight of the points
    within ``tolerance``. The best one is refined by weighted PCA of its inliers. CutError
    (naming ``where``) when the ball holds < 3 points, no hypothesis counts, or the inliers
    hold less than ``min_inlier_share`` of the ball's weight.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    w = np.asarray(weights, np.float64).reshape(-1)
    look_at, cams = np.asarray(look_at, np.float64), np.asarray(cameras, np.float64).reshape(-1, 3)
    ball = (np.linalg.norm(pts - look_at, axis=1) < radius) & (w > 0)
    p, pw = pts[ball], w[ball]
    if len(p) < 3:
        raise CutError(f"{where}: no support plane found: {len(p)} point(s) within "
                       f"{radius:.4g} of the cameras' look-at point {_fmt(look_at)}")
    rng = np.random.default_rng(seed)
    n, off = _hypotheses(p, pw, iterations, rng)
    n, off = _orient(n, off, look_at)
    ok = _admissible(n, off, look_at, cams, tolerance, up, max_tilt_deg)
    if not ok.any():
        raise CutError(f"{where}: no support plane found: none of {len(n)} candidate planes "
                       f"lies below the look-at point {_fmt(look_at)} with the cameras above it"
                       + ("" if up is None else f" and within {max_tilt_deg:g}° of the cameras' "
                          f"up {_fmt(up)}"))
    sub = rng.choice(len(p), min(len(p), _SCORE_POINTS), replace=False)
    score = _scores(p[sub], pw[sub], n[ok], off[ok], tolerance)
    best = int(np.flatnonzero(ok)[np.argmax(score)])
    normal, offset = _refine(p, pw, n[best], off[best], tolerance)
    normal, offset = _orient(normal[None], np.array([offset]), look_at)
    normal, offset = normal[0], float(offset[0])
    inl = np.abs(p @ normal + offset) < tolerance
    share = float(pw[inl].sum() / pw.sum())
    above = float(np.mean(cams @ normal + offset > 0))
    if share < min_inlier_share:
        raise CutError(f"{where}: no support plane found: the best plane holds {share:.1%} of "
                       f"the {len(p)} points near the look-at point within {tolerance:.4g} "
                       f"(need ≥ {min_inlier_share:.0%}; raise --plane-tolerance?)")
    return Plane(normal, offset, int(inl.sum()), share, float(tolerance), above)


def _hypotheses(p: np.ndarray, w: np.ndarray, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """[H, 3] unit normals and [H] offsets of planes through weighted-random point triples."""
    idx = rng.choice(len(p), size=(max(int(count), 1), 3), p=w / w.sum())
    a, b, c = p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    good = norm > 1e-12 * max(float(np.ptp(p, axis=0).max()), 1e-30) ** 2
    n = n[good] / norm[good, None]
    return n, -(n * a[good]).sum(1)


def _orient(n: np.ndarray, off: np.ndarray, look_at: np.ndarray):
    """Normals flipped so that the look-at point is on the positive side."""
    s = np.where(n @ look_at + off < 0, -1.0, 1.0)
    return n * s[:, None], off * s


def _admissible(n, off, look_at, cams, tol, up, max_tilt_deg) -> np.ndarray:
    ok = n @ look_at + off > tol
    ok &= ((cams @ n.T + off) > 0).mean(0) >= 0.8
    if up is not None:
        ok &= n @ np.asarray(up, np.float64) >= np.cos(np.radians(max_tilt_deg))
    return ok


def _scores(p, w, n, off, tol) -> np.ndarray:
    out = np.empty(len(n))
    for i in range(0, len(n), _CHUNK):
        d = np.abs(p @ n[i:i + _CHUNK].T + off[i:i + _CHUNK])          # [M, chunk]
        out[i:i + _CHUNK] = w @ (d < tol)
    return out


def _refine(p, w, n, off, tol):
    """Weighted PCA of the inliers, ``_REFINE`` times (the inliers re-selected each time)."""
    for _ in range(_REFINE):
        inl = np.abs(p @ n + off) < tol
        if inl.sum() < 3:
            break
        q, qw = p[inl], w[inl]
        c = (qw[:, None] * q).sum(0) / qw.sum()
        cov = (qw[:, None] * (q - c)).T @ (q - c)
        m = np.linalg.eigh(cov)[1][:, 0]
        n = m if m @ n >= 0 else -m
        off = -float(n @ c)
    return n, off


def plane_frame(plane: Plane, origin) -> np.ndarray:
    """[4, 4] world → plane frame: rows (e_x, e_y, n), ``origin``'s foot at 0.

    e_x is world +X projected onto the plane (world +Y when X is nearly normal to it), so
    the frame depends only on the plane and the origin."""
    n = plane.normal
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    ex = ref - (ref @ n) * n
    ex /= np.linalg.norm(ex)
    r = np.stack([ex, np.cross(n, ex), n])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, -r @ plane.foot(origin)
    return m


# ----------------------------------------------------------------------------- selection

@dataclasses.dataclass
class Selection:
    """The kept surfels and how they were found."""
    keep: np.ndarray            # [N] bool
    body: int                   # surfels above the slab in the grown component
    base: int                   # low surfels added under the body's footprint
    faint: int                  # low-opacity surfels attached afterwards
    seed_distance: float        # from the look-at point to the nearest kept body surfel
    components: list            # [(surfels, distance to the look-at point)] of each kept part


def grow_object(means, opacity, heights, look_at, *, radius: float, seed_distance: float,
                min_height: float, slab: float, footprint: float, min_opacity: float,
                min_component: int, to_plane, where: str = "surfels") -> Selection:
    """What stands on the plane near ``look_at`` (module docstring, step 3).

    means [N, 3], opacity [N] in [0, 1], heights [N] above the plane; ``to_plane`` [4, 4]
    (world → plane frame, :func:`plane_frame`; its first two rows place the footprint). Lengths in
    scene units: ``radius`` links surfels, ``seed_distance`` bounds the body's distance to
    the look-at point, ``min_height`` is the lowest kept height, ``slab`` the top of the low
    slab, ``footprint`` the horizontal reach of the body's footprint. Every component with a
    surfel within ``seed_distance`` is kept unless it has fewer than ``min_component``
    surfels (floaters). CutError naming ``where``
    when nothing above the slab lies within ``seed_distance`` of the look-at point.
    """
    from scipy.spatial import cKDTree
    x = np.asarray(means, np.float64)
    op, h = np.asarray(opacity, np.float64), np.asarray(heights, np.float64)
    solid = op >= min_opacity
    body_c = np.flatnonzero(solid & (h > slab))
    if len(body_c) == 0:
        raise CutError(f"{where}: nothing above the plane near the look-at point: no surfel "
                       f"of opacity ≥ {min_opacity:g} is more than {slab:.4g} above the plane")
    tree = cKDTree(x[body_c])
    dist = np.linalg.norm(x[body_c] - look_at, axis=1)
    order = np.argsort(dist)
    order = order[dist[order] <= seed_distance]
    if len(order) == 0:
        raise CutError(f"{where}: nothing above the plane near the look-at point "
                       f"{_fmt(look_at)}: the nearest surfel more than {slab:.4g} above the "
                       f"plane is {dist.min():.4g} away (limit {seed_distance:.4g}; pass "
                       "--object-box, or raise --seed-distance)")
    body, comps = _near_components(tree, x[body_c], order, dist, radius, min_component)
    if body is None:
        raise CutError(f"{where}: nothing above the plane near the look-at point: only "
                       f"fragments of < {min_component} surfels within {seed_distance:.4g} "
                       f"of {_fmt(look_at)} (lower --min-component or raise --grow-radius)")
    keep = np.zeros(len(x), bool)
    keep[body_c[body]] = True
    n_body = int(keep.sum())
    base = _base(x, h, keep, solid, min_height, slab, radius, footprint, to_plane)
    keep |= base
    faint = _faint(x, h, keep, solid, min_height, slab, radius)
    keep |= faint
    return Selection(keep, n_body, int(base.sum()), int(faint.sum()),
                     min(d for _, d in comps), comps)


def _grow(tree, pts: np.ndarray, start: np.ndarray, radius: float) -> np.ndarray:
    """[M] bool: the points of ``tree`` (``pts``) linked to ``start`` by hops ≤ ``radius``
    (breadth first)."""
    got = np.zeros(len(pts), bool)
    got[start] = True
    frontier = np.asarray(start, np.int64)
    while frontier.size:
        nb = tree.query_ball_point(pts[frontier], radius, return_sorted=False)
        cand = np.unique(np.fromiter((j for lst in nb for j in lst), np.int64))
        frontier = cand[~got[cand]]
        got[frontier] = True
    return got


def _near_components(tree, pts, order, dist, radius, min_component):
    """([M] bool, [(size, distance)]): the union of the components with ≥ ``min_component``
    points that have a seed in ``order`` (indices by increasing distance ``dist`` to the
    look-at point, all within reach), with their sizes and nearest distances; (None, [])
    when there is none."""
    seen = np.zeros(len(pts), bool)
    union, parts = np.zeros(len(pts), bool), []
    for i in order:
        if seen[i]:
            continue
        comp = _grow(tree, pts, np.array([i]), radius)
        seen |= comp
        if comp.sum() >= min_component:
            union |= comp
            parts.append((int(comp.sum()), float(dist[i])))
    return (union, parts) if parts else (None, [])


def _base(x, h, keep, solid, min_height, slab, radius, footprint, to_plane) -> np.ndarray:
    """Low solid surfels under the body's footprint, linked to the body through each other."""
    from scipy.spatial import cKDTree
    low = np.flatnonzero(solid & (h > min_height) & (h <= slab))
    out = np.zeros(len(x), bool)
    if len(low) == 0:
        return out
    r2 = np.asarray(to_plane, np.float64)[:2, :3]             # world -> plane (x, y)
    body = np.flatnonzero(keep)
    d2, _ = cKDTree(x[body] @ r2.T).query(x[low] @ r2.T, distance_upper_bound=footprint)
    under = low[np.isfinite(d2)]
    if len(under) == 0:
        return out
    pts = np.concatenate([x[body], x[under]])
    got = _grow(cKDTree(pts), pts, np.arange(len(body)), radius)
    out[under[got[len(body):]]] = True
    return out


def _faint(x, h, keep, solid, min_height, slab, radius) -> np.ndarray:
    """Faint surfels (below ``min_opacity``) within ``radius`` of a kept one, above
    ``min_height`` (above the slab, or beside a kept low surfel)."""
    from scipy.spatial import cKDTree
    cand = np.flatnonzero(~solid & (h > min_height))
    out = np.zeros(len(x), bool)
    if len(cand) == 0 or not keep.any():
        return out
    kept = np.flatnonzero(keep)
    d, j = cKDTree(x[kept]).query(x[cand], distance_upper_bound=radius)
    near = np.isfinite(d)
    ok = near & ((h[cand] > slab) | (h[kept[np.minimum(j, len(kept) - 1)]] <= slab))
    out[cand[ok]] = True
    return out


def link_radius(means, opacity, look_at, *, radius: float, reach: float, min_opacity: float,
                spacing_factor: float, k: int = 4) -> tuple[float, float]:
    """(link radius, spacing): at least ``radius``, and at least ``spacing_factor`` × the
    median distance of the solid surfels within ``reach`` of ``look_at`` to their ``k``-th
    nearest neighbour (``spacing``). A sparse reconstruction (a short step 1 from SfM
    points) is linked by its own spacing, a dense one by ``radius``."""
    from scipy.spatial import cKDTree
    x = np.asarray(means, np.float64)
    x = x[(np.asarray(opacity) >= min_opacity) & (np.linalg.norm(x - look_at, axis=1) < reach)]
    if len(x) <= k:
        return float(radius), 0.0
    spacing = float(np.median(cKDTree(x).query(x, k=k + 1)[0][:, -1]))
    return max(float(radius), spacing_factor * spacing), spacing


def box_selection(points_in_frame, box, where: str = "surfels", frame: str = "world",
                  span=None) -> np.ndarray:
    """[N] bool: points (already in the box's frame) inside ``box`` (xmin ymin zmin xmax
    ymax zmax). CutError when it holds none; ``span`` (lo, hi) is named in the message."""
    p = np.asarray(points_in_frame, np.float64)
    lo, hi = np.asarray(box[:3], np.float64), np.asarray(box[3:], np.float64)
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    if not inside.any():
        tail = "" if span is None else (f"; the surfels span {_fmt(span[0])} to "
                                        f"{_fmt(span[1])} in that frame")
        raise CutError(f"{where}: the box {_fmt(lo)} to {_fmt(hi)} ({frame} frame) holds no "
                       f"surfel{tail}")
    return inside


# ----------------------------------------------------------------------------- measures

def cut_measures(heights, opacity, normals, plane_normal, keep, slab: float) -> dict:
    """Opacity-weighted shares of the kept surfels: ``below`` the plane (h < 0),
    ``slab`` (0 ≤ h ≤ ``slab``), ``flat_slab`` (in the slab with the normal within
    ``FLAT_DEG`` of the plane normal, either sign: floor or sheet remnants); with the kept
    count, weight and height (99.5th percentile)."""
    h = np.asarray(heights, np.float64)[keep]
    w = np.asarray(opacity, np.float64)[keep]
    cosn = np.abs(np.asarray(normals, np.float64)[keep] @ np.asarray(plane_normal, np.float64))
    total = max(float(w.sum()), 1e-30)
    in_slab = (h >= 0) & (h <= slab)
    flat = cosn >= np.cos(np.radians(FLAT_DEG))
    return {"kept": int(keep.sum()), "kept_weight": float(w.sum()),
            "below_share": float(w[h < 0].sum() / total),
            "slab_share": float(w[in_slab].sum() / total),
            "flat_slab_share": float(w[in_slab & flat].sum() / total),
            "slab_height": float(slab),
            "height": float(np.percentile(h, 99.5)) if len(h) else 0.0}


def _fmt(v) -> str:
    return "(" + ", ".join(f"{float(a):.4g}" for a in np.ravel(v)) + ")"
