"""Fixed-radius K-nearest probe search and interpolation weights (paper eq. knn).

At a shading point x with unit normal n, the Surface Octahedral Probes k that lie within
the query radius r (‖d_k‖ ≤ r, d_k = p_k − x) are found, at most ``k`` of them are kept
(the nearest), and each gets the weight

    w_k = w_s · w_b,    w_s = 1 / max(‖d_k‖, ε),
    w_b = 0.5 · (1 + (d_k / max(‖d_k‖, ε)) · n) + 0.01,    ε = EPS_REL · r,

normalised so that the kept weights sum to 1. The clamp ε keeps the weight of a probe that
sits exactly on x finite (its back-face term is then 0.51).

Empty neighbourhood rule: a point with *no* probe within r gets its single nearest probe
overall (any distance) with weight 1 and ``fallback = True``. Those points are rare; they
are answered on the CPU with ``scipy.spatial.cKDTree`` (built once per grid, lazily).

Search structure (:class:`ProbeGrid`, built once per probe set with numpy): a uniform grid
with cell size h = r. If the probes' bounding box needs at most ``max_dense_cells`` cells
the grid is dense (cell id = (z·ny + y)·nx + x); otherwise cells are hashed into a
power-of-two table of buckets. Probes are sorted by cell/bucket (argsort), so each cell
or bucket is a contiguous range ``[cell_start[c], cell_start[c+1])`` of the sorted arrays.
In the dense grid the cells of one row (fixed y, z) are consecutive, so a query visits at
most 9 contiguous row ranges instead of 27 cells; in the hashed grid it visits each cell
of its box and keeps only probes whose own cell is the visited one (bucket collisions
cost time, never duplicates).

The query (Dr.Jit, vectorised over points) is one symbolic ``dr.while_loop`` whose state
is the current range (pointer, end), the next row/cell to visit, the count of probes
within r, and a sorted top-k list of (d², sorted position), updated by an unrolled
insertion. The cell range of a point is [cell(x − r'), cell(x + r')] per axis (r' = r
slightly enlarged), where ``cell(v) = floor((v − o) · (1/h))`` is evaluated by the same
float32 Dr.Jit code for probes (at build time) and for queries. Rounding to nearest is
monotone, so every probe with |p − x| ≤ r per axis lies in that range: no probe within
the radius can be missed because of rounding at a cell boundary.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.spatial import cKDTree

from comgs_dr.core.hostarray import to_jit

__all__ = ["ProbeGrid", "KnnResult", "query", "interpolate", "brute_force_query",
           "EPS_REL", "BACKFACE_FLOOR"]

EPS_REL = 1e-6          # ε = EPS_REL · radius: lower clamp of ‖d_k‖ in the weights
BACKFACE_FLOOR = 0.01   # the "+ 0.01" of the back-face weight w_b
MAX_DENSE_CELLS = 1 << 22
_BOX_PAD = 1e-5         # the cell range is computed for radius·(1 + _BOX_PAD)
_HASH_CLAMP = float(1 << 30)
_PRIMES = (73856093, 19349663, 83492791)


def _cell(v, origin: float, inv_cell: float, lo: float, hi: float):
    """Cell coordinate (mi.Int32) of the float32 coordinates ``v`` along one axis.

    The single definition used for probes and queries (see the module docstring)."""
    u = dr.clip((v - origin) * inv_cell, lo, hi)
    return mi.Int32(dr.floor(u))


def _hash(cx, cy, cz, mask: int):
    """Bucket of the integer cell (cx, cy, cz) in a table of ``mask + 1`` buckets."""
    ux = dr.reinterpret_array(mi.UInt32, cx) * _PRIMES[0]
    uy = dr.reinterpret_array(mi.UInt32, cy) * _PRIMES[1]
    uz = dr.reinterpret_array(mi.UInt32, cz) * _PRIMES[2]
    return (ux ^ uy ^ uz) & mask


@dataclass(eq=False)
class ProbeGrid:
    """Uniform grid (cell size = ``radius``) over probe positions, for :func:`query`.

    ``positions``: [P, 3] probe positions (stored as float32); ``radius`` > 0: the fixed
    query radius. ``max_dense_cells``: above this many cells over the bounding box the
    grid is hashed instead of dense.

    Derived (Dr.Jit arrays): ``sorted_index`` [P] probe ids sorted by cell/bucket,
    ``sorted_pos`` [P] their positions in that order, ``cell_start`` [C+1] range offsets
    (cell c holds sorted entries ``cell_start[c] … cell_start[c+1]-1``; C = number of
    dense cells or hash buckets).
    """
    positions: np.ndarray
    radius: float
    max_dense_cells: int = MAX_DENSE_CELLS

    hashed: bool = field(init=False)
    origin: tuple = field(init=False)          # (ox, oy, oz) float32 values
    inv_cell: float = field(init=False)        # 1 / h as a float32 value
    dims: tuple = field(init=False)            # dense: (nx, ny, nz); hashed: ()
    table_size: int = field(init=False)        # number of cells (dense) or buckets
    sorted_index: object = field(init=False, repr=False)
    sorted_pos: object = field(init=False, repr=False)
    cell_start: object = field(init=False, repr=False)
    _kdtree: object = field(init=False, repr=False, default=None)

    def __post_init__(self):
        pos = np.asarray(self.positions)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"ProbeGrid: positions must be [P, 3], got shape {pos.shape}")
        if len(pos) == 0:
            raise ValueError("ProbeGrid: no probes (positions is empty)")
        if len(pos) >= 1 << 31:
            raise ValueError(f"ProbeGrid: too many probes ({len(pos)})")
        pos = np.ascontiguousarray(pos, np.float32)
        if not np.isfinite(pos).all():
            bad = int((~np.isfinite(pos).all(axis=1)).sum())
            raise ValueError(f"ProbeGrid: {bad} probe position(s) hold NaN or Inf")
        try:
            radius = float(self.radius)
        except (TypeError, ValueError):
            raise ValueError(f"ProbeGrid: radius must be a number, got {self.radius!r}")
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"ProbeGrid: radius must be finite and > 0, got {self.radius!r}")
        self.positions, self.radius = pos, radius
        h = float(np.float32(radius))
        if h <= 0:  # below float32's range
            raise ValueError(f"ProbeGrid: radius {radius!r} underflows float32")
        self.inv_cell = float(np.float32(1.0 / h))
        lo, hi = pos.min(axis=0), pos.max(axis=0)
        self.origin = tuple(float(v) for v in lo)
        est = np.floor((hi.astype(np.float64) - lo) / h) + 2
        self.hashed = bool(np.prod(est) > self.max_dense_cells)

        P = len(pos)
        with dr.suspend_grad():
            comps = [to_jit(mi.Float, pos[:, a]) for a in range(3)]
            if self.hashed:
                cells = [_cell(comps[a], self.origin[a], self.inv_cell,
                               -_HASH_CLAMP, _HASH_CLAMP) for a in range(3)]
                self.table_size = 1 << max(int(np.ceil(np.log2(2 * P))), 1)
                key = _hash(*cells, self.table_size - 1)
                self.dims = ()
            else:
                big = float(np.float32(est.max() + 4))
                cells = [_cell(comps[a], self.origin[a], self.inv_cell, -1.0, big)
                         for a in range(3)]
                dims = [int(dr.max(c)[0]) + 1 for c in cells]   # cell(min) = 0
                self.dims = tuple(dims)
                self.table_size = dims[0] * dims[1] * dims[2]
                nx, ny = dims[0], dims[1]
                key = mi.UInt32((cells[2] * ny + cells[1]) * nx + cells[0])
            key = np.asarray(key, np.int64)
        order = np.argsort(key, kind="stable")
        counts = np.bincount(key, minlength=self.table_size)
        start = np.zeros(self.table_size + 1, np.uint32)
        np.cumsum(counts, out=start[1:])
        self.sorted_index = to_jit(mi.UInt32, order)
        self.sorted_pos = to_jit(mi.Point3f, pos[order].T)
        self.cell_start = to_jit(mi.UInt32, start)
        dr.eval(self.sorted_index, self.sorted_pos, self.cell_start)

    @property
    def count(self) -> int:
        """Number of probes P."""
        return len(self.positions)

    @property
    def cell_count(self):
        """Probes per cell/bucket (``mi.UInt32`` [C])."""
        c = np.asarray(self.cell_start, np.int64)
        return to_jit(mi.UInt32, c[1:] - c[:-1])

    def kdtree(self):
        """scipy cKDTree over the probes (built on first use; fallback queries)."""
        if self._kdtree is None:
            self._kdtree = cKDTree(self.positions.astype(np.float64))
        return self._kdtree


@dataclass(eq=False)
class KnnResult:
    """Neighbours and weights of N points, ``k`` slots each, flat and row-major.

    ``index`` [N·k] probe ids (slot j of point i at i·k + j, nearest first; unused slots
    hold probe 0 with weight 0, so gathers through them are safe), ``weight`` [N·k]
    normalised weights, ``count`` [N] number of probes within the radius (*not* capped
    at k; slots used = min(count, k), or 1 for a fallback), ``fallback`` [N] True where
    no probe was within the radius and the nearest probe overall was used (weight 1).
    """
    index: object          # mi.UInt32 [N*k]
    weight: object         # mi.Float  [N*k]
    count: object          # mi.UInt32 [N]
    fallback: object       # mi.Bool   [N]
    k: int
    n_fallback: int
    num_probes: int

    @property
    def size(self) -> int:
        """Number of query points N."""
        return dr.width(self.count)

    def numpy(self):
        """(index [N,k] int64, weight [N,k] float32, count [N], fallback [N]) as numpy."""
        n = dr.width(self.count)
        return (np.asarray(self.index, np.int64).reshape(n, self.k),
                np.asarray(self.weight, np.float32).reshape(n, self.k),
                np.asarray(self.count, np.int64).reshape(n),
                np.asarray(self.fallback, bool).reshape(n))


def _check_finite(x, n) -> None:
    def bad(v):
        return ~(dr.isfinite(v.x) & dr.isfinite(v.y) & dr.isfinite(v.z))
    if int(dr.count(bad(x) | bad(n))[0]) == 0:     # one reduction in the common case
        return
    for arr, what in ((x, "points"), (n, "normals")):
        cnt = int(dr.count(bad(arr))[0])
        if cnt:
            raise ValueError(f"query: {cnt} of {dr.width(arr)} {what} are not finite "
                             "(NaN/Inf); mask them out before the probe query")


def query(grid: ProbeGrid, points, normals, k: int = 8) -> KnnResult:
    """K nearest probes within ``grid.radius`` of each point, with eq.-knn weights.

    ``points`` ``mi.Point3f`` [N], ``normals`` ``mi.Vector3f`` [N] (unit; or width 1).
    Runs without gradients (inputs are detached). Raises ``ValueError`` if any point or
    normal is NaN/Inf (the message says how many).

    * A probe counts as a neighbour iff ‖p − x‖ ≤ radius (float32 distances); the
      nearest ``k`` are kept, sorted by distance (ties in any order).
    * Weights: w = 1/max(‖d‖, ε) · (0.5·(1 + d·n / max(‖d‖, ε)) + 0.01), ε = 1e-6·radius
      (finite even for a point exactly on a probe), normalised to sum to 1.
    * No probe within the radius: the nearest probe overall (cKDTree, on the CPU, for
      those points only) in slot 0 with weight 1, ``fallback`` True; the number of such
      points is ``result.n_fallback``.
    """
    if not isinstance(grid, ProbeGrid):
        raise TypeError(f"query: grid must be a ProbeGrid, got {type(grid).__name__}")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"query: k must be an integer ≥ 1, got {k!r}")
    k = int(k)
    with dr.suspend_grad():
        x = mi.Point3f(dr.detach(points))
        n = mi.Vector3f(dr.detach(normals))
        N = dr.width(x)
        if dr.width(n) not in (N, 1):
            raise ValueError(f"query: {N} points but {dr.width(n)} normals")
        if N == 0:
            return KnnResult(mi.UInt32(), mi.Float(), mi.UInt32(), mi.Bool(), k, 0,
                             grid.count)
        _check_finite(x, n)
        dist, slot, count = _search(grid, x, k)
        dr.eval(count, dist, slot)
        index, weight = _weights(grid, x, n, dist, slot, k)
        fallback = count == 0
        dr.eval(index, weight, fallback)
        n_fb = int(dr.count(fallback)[0])
        if n_fb:
            ids = dr.compress(fallback)
            xp = dr.gather(mi.Point3f, x, ids)
            dr.eval(xp)
            pts = np.stack([np.asarray(xp.x), np.asarray(xp.y), np.asarray(xp.z)], 1)
            _, nn = grid.kdtree().query(pts.astype(np.float64), k=1)
            dr.scatter(index, to_jit(mi.UInt32, nn), ids * k)
            dr.scatter(weight, mi.Float(1.0), ids * k)
            dr.eval(index, weight)
    return KnnResult(index, weight, count, fallback, k, n_fb, grid.count)


def _search(grid: ProbeGrid, x, k: int):
    """The symbolic loop: (dist² [k] sorted ascending, sorted positions [k], count)."""
    # Grid constants enter the kernel as opaque (non-literal) values, so one compiled
    # kernel serves every grid and radius (per k and dense/hashed).
    def f(v):
        return dr.opaque(mi.Float, float(np.float32(v)))

    def i(v):
        return dr.opaque(mi.Int32, int(v))

    with np.errstate(over="ignore"):        # radius > 1.8e19: r² = inf, every probe is in
        r2 = f(np.float32(grid.radius) ** 2)
    rb = f(grid.radius * (1.0 + _BOX_PAD))
    o = [f(v) for v in grid.origin]
    s = f(grid.inv_cell)
    comps = (x.x, x.y, x.z)
    if grid.hashed:
        clo, chi = f(-_HASH_CLAMP), f(_HASH_CLAMP)
        lo = [_cell(comps[a] - rb, o[a], s, clo, chi) for a in range(3)]
        hi = [_cell(comps[a] + rb, o[a], s, clo, chi) for a in range(3)]
        mask = dr.opaque(mi.UInt32, grid.table_size - 1)
    else:
        dims = grid.dims
        lo = [dr.maximum(_cell(comps[a] - rb, o[a], s, f(-1.0), f(dims[a])), 0)
              for a in range(3)]
        hi = [dr.minimum(_cell(comps[a] + rb, o[a], s, f(-1.0), f(dims[a])), i(dims[a] - 1))
              for a in range(3)]
        empty = (lo[0] > hi[0]) | (lo[1] > hi[1]) | (lo[2] > hi[2])
        nx, ny = i(dims[0]), i(dims[1])

    inf = float("inf")
    N = dr.width(x)
    zero_u = dr.zeros(mi.UInt32, N)
    # next cell/row to visit: (cx, cy, cz); the loop is done when cz > hi_z
    cz0 = mi.Int32(lo[2]) if grid.hashed else dr.select(empty, hi[2] + 1, lo[2])
    state = (mi.UInt32(zero_u), mi.UInt32(zero_u),            # ptr, end
             mi.Int32(lo[0]), mi.Int32(lo[1]), cz0,             # next cell / row
             (mi.Int32(lo[0]), mi.Int32(lo[1]), mi.Int32(lo[2])),  # current cell (hashed)
             mi.UInt32(zero_u),                                 # count within radius
             tuple(dr.full(mi.Float, inf, N) for _ in range(k)),
             tuple(mi.UInt32(zero_u) for _ in range(k)))

    def cond(ptr, end, cx, cy, cz, cur, count, dist, slot):
        return (ptr < end) | (cz <= hi[2])

    def body(ptr, end, cx, cy, cz, cur, count, dist, slot):
        # 1. current range exhausted: move to the next row (dense) or cell (hashed)
        adv = (ptr >= end) & (cz <= hi[2])
        if grid.hashed:
            b = _hash(cx, cy, cz, mask)
            nptr = dr.gather(mi.UInt32, grid.cell_start, b, adv)
            nend = dr.gather(mi.UInt32, grid.cell_start, b + 1, adv)
            cur = tuple(dr.select(adv, c, c0) for c, c0 in zip((cx, cy, cz), cur))
            ncx = cx + 1
            wx = ncx > hi[0]
            ncy = dr.select(wx, cy + 1, cy)
            wy = ncy > hi[1]
            cx = dr.select(adv, dr.select(wx, lo[0], ncx), cx)
            cy = dr.select(adv, dr.select(wy, lo[1], ncy), cy)
            cz = dr.select(adv & wy, cz + 1, cz)
        else:
            row = mi.UInt32((cz * ny + cy) * nx)
            a = row + mi.UInt32(lo[0])
            e = row + mi.UInt32(hi[0]) + 1
            nptr = dr.gather(mi.UInt32, grid.cell_start, a, adv)
            nend = dr.gather(mi.UInt32, grid.cell_start, e, adv)
            ncy = cy + 1
            wy = ncy > hi[1]
            cy = dr.select(adv, dr.select(wy, lo[1], ncy), cy)
            cz = dr.select(adv & wy, cz + 1, cz)
        ptr = dr.select(adv, nptr, ptr)
        end = dr.select(adv, nend, end)

        # 2. test the probe at ptr and insert it into the sorted top-k list
        live = ptr < end
        p = dr.gather(mi.Point3f, grid.sorted_pos, ptr, live)
        d2 = dr.squared_norm(p - x)
        ok = live & (d2 <= r2)
        if grid.hashed:   # only probes of the visited cell (bucket collisions)
            pc = (p.x, p.y, p.z)
            for a in range(3):
                ok &= _cell(pc[a], o[a], s, clo, chi) == cur[a]
        count = dr.select(ok, count + 1, count)
        ins = ok & (d2 < dist[k - 1])
        nd, ns = [], []
        for j in range(k):
            put = ins & (d2 < dist[j])
            if j == 0:
                nd.append(dr.select(put, d2, dist[0]))
                ns.append(dr.select(put, ptr, slot[0]))
            else:
                shift = ins & (d2 < dist[j - 1])     # candidate lands before slot j-1
                nd.append(dr.select(shift, dist[j - 1], dr.select(put, d2, dist[j])))
                ns.append(dr.select(shift, slot[j - 1], dr.select(put, ptr, slot[j])))
        ptr = dr.select(live, ptr + 1, ptr)
        return ptr, end, cx, cy, cz, cur, count, tuple(nd), tuple(ns)

    out = dr.while_loop(state, cond, body, label="sop_knn")
    return list(out[7]), list(out[8]), out[6]


def _weights(grid: ProbeGrid, x, n, dist, slot, k: int):
    """Flat (index, weight) [N·k] from the top-k lists (before the fallback fix-up)."""
    N = dr.width(x)
    eps = dr.opaque(mi.Float, EPS_REL * grid.radius)
    base = dr.arange(mi.UInt32, N) * k
    ids, ws = [], []
    total = mi.Float(0.0)
    for j in range(k):
        used = dist[j] < float("inf")
        ids.append(dr.gather(mi.UInt32, grid.sorted_index, slot[j], used))   # 0 if unused
        p = dr.gather(mi.Point3f, grid.sorted_pos, slot[j], used)
        d = p - x
        length = dr.maximum(dr.norm(d), eps)
        w = (1.0 / length) * (0.5 * (1.0 + dr.dot(d, n) / length) + BACKFACE_FLOOR)
        w = dr.select(used, w, 0.0)
        ws.append(w)
        total += w
    inv = dr.select(total > 0, dr.rcp(total), 0.0)
    ws = [w * inv for w in ws]
    if k == 1:
        return mi.UInt32(ids[0]), mi.Float(ws[0])
    # One packet scatter per output (order='F': point-major, slots alternate). k separate
    # dr.scatter calls into one target would each launch a kernel (pending plain
    # scatters to a target force evaluation), recomputing the weights every time.
    return (dr.ravel(mi.ArrayXu(*ids), order="F"), dr.ravel(mi.ArrayXf(*ws), order="F"))


def interpolate(result: KnnResult, values, mode=dr.ReduceMode.Expand):
    """Σ_j w_j · values[index_j] per point: ``values`` is a per-probe Dr.Jit array
    (``mi.Float``, ``mi.Color3f``, ``mi.Vector4f``, … of width P), differentiable w.r.t.
    ``values``; the gathers' reverse-mode scatter-adds use ``mode`` (Expand: non-atomic
    per-thread copies on LLVM). Zero-weight slots are masked out of the gathers."""
    if dr.width(values) != result.num_probes:
        raise ValueError(f"interpolate: values has width {dr.width(values)}, expected one "
                         f"entry per probe ({result.num_probes})")
    tp = type(values)
    N, k = dr.width(result.count), result.k
    base = dr.arange(mi.UInt32, N) * k
    acc = None
    for j in range(k):
        idx = dr.gather(mi.UInt32, result.index, base + j)
        w = dr.gather(mi.Float, result.weight, base + j)
        v = dr.gather(tp, values, idx, w > 0, mode=mode)
        acc = w * v if acc is None else acc + w * v
    return acc


# ---------------------------------------------------------------------------------------
# Reference (numpy, float64, O(N·P)): the obviously right version, for tests.

def brute_force_query(probes_np, points_np, normals_np, radius: float, k: int = 8,
                      chunk: int = 1024):
    """Same contract as :func:`query`, by exhaustive search in float64.

    Returns numpy (index [N,k] int64, weight [N,k] float64, count [N], fallback [N]).
    """
    probes = np.asarray(probes_np, np.float64).reshape(-1, 3)
    pts = np.asarray(points_np, np.float64).reshape(-1, 3)
    nrm = np.broadcast_to(np.asarray(normals_np, np.float64).reshape(-1, 3), pts.shape)
    if len(probes) == 0:
        raise ValueError("brute_force_query: no probes")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"brute_force_query: radius must be finite and > 0, got {radius!r}")
    if not np.isfinite(pts).all():
        raise ValueError("brute_force_query: points hold NaN/Inf")
    N, P, eps = len(pts), len(probes), EPS_REL * radius
    kk = min(k, P)
    index = np.zeros((N, k), np.int64)
    weight = np.zeros((N, k), np.float64)
    count = np.zeros(N, np.int64)
    fallback = np.zeros(N, bool)
    rows = np.arange(N)
    for s in range(0, N, chunk):
        x, nn, r = pts[s:s + chunk], nrm[s:s + chunk], rows[s:s + chunk]
        d = probes[None, :, :] - x[:, None, :]                    # [n, P, 3]
        dist = np.sqrt((d * d).sum(-1))                            # [n, P]
        inside = dist <= radius
        count[r] = inside.sum(1)
        masked = np.where(inside, dist, np.inf)
        near = np.argpartition(masked, kk - 1, axis=1)[:, :kk]     # the kk smallest
        near = np.take_along_axis(
            near, np.argsort(np.take_along_axis(masked, near, 1), 1, kind="stable"), 1)
        used = np.isfinite(np.take_along_axis(masked, near, 1))    # within the radius
        length = np.maximum(np.take_along_axis(dist, near, 1), eps)
        dk = np.take_along_axis(d, near[:, :, None], 1)            # [n, kk, 3]
        cos = (dk * nn[:, None, :]).sum(-1) / length
        w = np.where(used, (1.0 / length) * (0.5 * (1.0 + cos) + BACKFACE_FLOOR), 0.0)
        total = w.sum(1, keepdims=True)
        index[r, :kk] = np.where(used, near, 0)
        weight[r, :kk] = np.divide(w, total, out=np.zeros_like(w), where=total > 0)
        empty = count[r] == 0                                       # nearest overall
        fallback[r] = empty
        index[r[empty], 0] = np.argmin(dist[empty], axis=1)
        weight[r[empty], 0] = 1.0
    return index, weight, count, fallback
