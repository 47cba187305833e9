"""Tile rasterisation of pinhole camera rays: the hit-finding step of ``surfel_gbuffer``.

The tracer (:func:`comgs_dr.surfels.composite.trace_composite`) finds the k-th hit of a
ray with a k-th BVH traversal; for a pinhole camera every ray of a tile of pixels meets
the same few surfels, so they are found by binning instead (as 2DGS/3DGS rasterise):

1. :func:`bin_surfels` — project each surfel's ±3σ proxy quad (clipped to the near
   plane) to the film, emit one (tile, depth) entry per overlapped 16×16 tile, sort the
   entries by tile, then by the view depth of the surfel centre (a stable 16-bit radix
   sort: ``np.argsort(kind="stable")``; indices need no gradient).
2. :func:`raster_hits` — per ray, walk its tile's list front to back with the exact
   ray–surfel intersection of :mod:`comgs_dr.surfels.kernel`, keep the hits of the ±3σ
   proxy quad (shifted along n by the shape's proxy jitter, as the tracer's) with
   α ≥ 1/255, inserted by the proxy's ray distance t into a K-slot local buffer, and
   stop once K hits are found or the transmittance Π(1 − α) of the found hits falls
   below ``T_MIN`` (a product: independent of the order).

Only hit finding changes: the hit buffer feeds the same differentiable compositing
(:func:`comgs_dr.surfels.composite.composite_hits` and ``composite_adjoint``), so
values and gradients are those of the tracer for the same hit list. The hit lists equal
the tracer's (coplanar surfels, e.g. of ``from_mesh`` faces, in the order of their
jittered proxies, as the tracer finds them) up to ties: hits at the ±3σ border or at
α = 1/255 within float rounding, and hits the tracer misses because their proxy lies
within its origin step (ε or ~4 ulps) of another one (``tests/test_raster.py`` checks
the agreement).

Binning runs in NumPy (O(N) projection, one stable radix sort of the entries); the
walk is one Dr.Jit kernel. Written by hand because no library rasterises 2D Gaussian
surfels for Dr.Jit.
"""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels import kernel as Kn
from comgs_dr.surfels.composite import INVALID, HitBuffer
from comgs_dr.surfels.shape import _finite_rest, proxy_shift

TILE = 8                  # tile side in pixels
_MARGIN_PX = 0.05          # bounding boxes grow by this much (float error of the fitted projection)
_NEAR_FRACTION = 0.999     # quads are clipped at this fraction of the near-clip distance
MAX_PASSES = 16            # walks of K hits per ray at most (raster_all_hits)


class NotPinhole(ValueError):
    """The sensor is not a pinhole perspective camera (use ``method='trace'``)."""


@dataclasses.dataclass
class PinholeView:
    """World → film-pixel projection of a pinhole sensor.

    A camera-space point c = M (x − C) projects to film pixels
    ``A @ [c.x / c.z, c.y / c.z, 1]`` (full-film coordinates, as ``pos`` of Mitsuba's
    ``sample_rays``); only points with c.z ≥ ``near`` can be hit.
    """
    M: np.ndarray            # [3, 3] world → camera (rows)
    C: np.ndarray            # [3] camera centre
    A: np.ndarray            # [2, 3] camera plane → film pixels
    near: float
    crop_offset: tuple[int, int]
    crop_size: tuple[int, int]

    @property
    def tiles(self) -> tuple[int, int]:
        return (-(-self.crop_size[0] // TILE), -(-self.crop_size[1] // TILE))


def is_pinhole(sensor) -> bool:
    """True for Mitsuba's ``perspective`` sensor (no aperture sample)."""
    return sensor.class_name() == "PerspectiveCamera" and not sensor.needs_aperture_sample()


def pinhole_view(sensor) -> PinholeView:
    """The projection of a ``perspective`` sensor, fitted from its own rays.

    Fitting (rather than re-deriving Mitsuba's camera-to-sample matrix) follows the sensor
    exactly, principal-point offsets and crop windows included; a residual above 1e-3 px
    on a 5×5 grid of rays means the sensor is no pinhole and raises :class:`NotPinhole`.
    """
    if not is_pinhole(sensor):
        raise NotPinhole(f"surfel_gbuffer: raster needs a 'perspective' sensor without "
                         f"aperture, got {sensor.class_name()}")
    film = sensor.film()
    full = np.array(film.size(), np.float64)
    to_world = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    inv = np.linalg.inv(to_world)
    M, C = inv[:3, :3], to_world[:3, 3]
    g = np.linspace(0.0, 1.0, 5)
    pos = np.stack(np.meshgrid(g * full[0], g * full[1], indexing="xy"), -1).reshape(-1, 2)
    with dr.suspend_grad():
        off = np.array(film.crop_offset(), np.float64)              # sample2 spans the crop
        crop = np.array(film.crop_size(), np.float64)
        smp = (pos - off) / crop
        ray, _ = sensor.sample_ray(0.0, 0.0, to_jit(mi.Point2f, smp.T), mi.Point2f(0.5))
    d = np.array(ray.d, np.float64).reshape(3, -1).T                      # [25, 3]
    c = d @ M.T
    if np.any(c[:, 2] <= 0):
        raise NotPinhole("surfel_gbuffer: sensor rays do not all look forward")
    X = np.c_[c[:, 0] / c[:, 2], c[:, 1] / c[:, 2], np.ones(len(c))]     # [25, 3]
    A, *_ = np.linalg.lstsq(X, pos, rcond=None)
    if np.abs(X @ A - pos).max() > 1e-3:
        raise NotPinhole("surfel_gbuffer: sensor rays are not those of a pinhole camera")
    o = np.array(ray.o, np.float64).reshape(3, -1).T
    near = float(np.min(((o - C) @ M.T)[:, 2]))
    return PinholeView(M=M, C=C, A=A.T, near=max(near, 0.0),
                       crop_offset=tuple(int(v) for v in film.crop_offset()),
                       crop_size=tuple(int(v) for v in film.crop_size()))


@dataclasses.dataclass
class SurfelGeometry:
    """Per-surfel frame of every surfel shape, concatenated (Dr.Jit arrays, [N_total]).

    ``proxy`` is the centre of the tracer's proxy quad: p shifted along n by the shape's
    per-surfel proxy jitter (as :func:`comgs_dr.surfels.shape.quad_buffers` does).
    """
    p: mi.Point3f
    proxy: mi.Point3f
    t_u: mi.Vector3f
    t_v: mi.Vector3f
    n: mi.Vector3f
    s: mi.Vector2f
    op: mi.Float
    keep: np.ndarray                 # [N_total] bool: finite and peak opacity ≥ 1/255
    slot: mi.UInt32                  # [N_total] which shape
    local: mi.UInt32                 # [N_total] index within its shape
    n_shapes: int


def surfel_geometry(shapes) -> SurfelGeometry:
    """Frames, scales and opacities as :func:`~comgs_dr.surfels.composite.eval_surfel`
    computes them (same kernel functions), for all shapes."""
    parts = {k: [] for k in ("p", "proxy", "t_u", "t_v", "n", "s", "op", "keep", "slot",
                             "local")}
    with dr.suspend_grad():
        for j, sh in enumerate(shapes):
            p = sh.params
            m = dr.width(p.opacity_logit)
            q = mi.Vector4f(dr.detach(p.quats))
            t_u, t_v, n = Kn.quat_frame(q)
            s = Kn.scales(mi.Vector2f(dr.detach(p.log_scales)))
            op = Kn.opacity(mi.Float(dr.detach(p.opacity_logit)))
            mean = mi.Point3f(dr.detach(p.means))
            idx = dr.arange(mi.UInt32, m)
            ok = (dr.all(dr.isfinite(mean)) & dr.all(dr.isfinite(q)) & dr.isfinite(op)
                  & dr.all(dr.isfinite(s)) & _finite_rest(p, idx) & (op >= Kn.ALPHA_MIN))
            proxy = mean + n * proxy_shift(idx, sh.proxy_jitter)
            for k, v in (("p", mean), ("proxy", proxy), ("t_u", t_u), ("t_v", t_v), ("n", n),
                         ("s", s), ("op", op)):
                parts[k].append(np.array(v, np.float32).reshape(-1, m).T if k != "op"
                                else np.array(v, np.float32))
            parts["keep"].append(np.array(ok, bool))
            parts["slot"].append(np.full(m, j, np.uint32))
            parts["local"].append(np.arange(m, dtype=np.uint32))
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    vec = {"p": mi.Point3f, "proxy": mi.Point3f, "t_u": mi.Vector3f, "t_v": mi.Vector3f,
           "n": mi.Vector3f, "s": mi.Vector2f}
    return SurfelGeometry(**{k: to_jit(T, cat[k].T) for k, T in vec.items()},
                          op=to_jit(mi.Float, cat["op"]), keep=cat["keep"],
                          slot=to_jit(mi.UInt32, cat["slot"]),
                          local=to_jit(mi.UInt32, cat["local"]), n_shapes=len(shapes))


@dataclasses.dataclass
class TileLists:
    """Entries sorted by (tile, centre depth): surfel ids and each tile's [start, end)."""
    ids: mi.UInt32          # [E] global surfel index
    keys: mi.Float          # [E] lower bound of the ray distance t of the entry's hits
    box: mi.Vector4f        # [E] film-pixel bounding box (x0, x1, y0, y1) of the entry's quad
    start: mi.UInt32        # [tiles]
    end: mi.UInt32          # [tiles]
    entries: int


def _project(geo: SurfelGeometry, view: PinholeView):
    """Film-pixel boxes [N, 4] (x0, x1, y0, y1) of the ±3σ proxy quads clipped to the near
    plane, [N] bool visible (some part in front of it) and [N] depth keys (a lower bound of
    the ray distance t of any hit, see :func:`bin_surfels`). One Dr.Jit kernel."""
    with dr.suspend_grad():
        M = mi.ScalarMatrix3f(view.M.astype(np.float32))
        C = mi.ScalarPoint3f(view.C.astype(np.float32))
        A = view.A.astype(np.float32).tolist()      # floats: np.float32 * mi.Float is a numpy array
        zc = float(view.near * _NEAR_FRACTION)
        eu = geo.t_u * (geo.s.x * Kn.QUAD_SIGMA)
        ev = geo.t_v * (geo.s.y * Kn.QUAD_SIGMA)
        corners = [M @ (geo.proxy - C + eu * a + ev * b)
                   for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]     # camera space
        inf = float("inf")
        x0, x1, y0, y1 = mi.Float(inf), mi.Float(-inf), mi.Float(inf), mi.Float(-inf)
        vis = mi.Bool(False)
        for k in range(4):                       # each edge a → b: a if in front, crossing
            pa, pb = corners[k], corners[(k + 1) % 4]
            za, zb = pa.z - zc, pb.z - zc
            cross = (za * zb) < 0
            w = dr.select(cross, za / dr.select(cross, za - zb, 1.0), 0.0)
            for q, valid in ((pa, za >= 0), (pa + (pb - pa) * w, cross)):
                z = dr.select(valid, dr.maximum(q.z, zc), 1.0)
                x, y = q.x / z, q.y / z
                fx = A[0][0] * x + A[0][1] * y + A[0][2]
                fy = A[1][0] * x + A[1][1] * y + A[1][2]
                x0 = dr.select(valid, dr.minimum(x0, fx), x0)
                x1 = dr.select(valid, dr.maximum(x1, fx), x1)
                y0 = dr.select(valid, dr.minimum(y0, fy), y0)
                y1 = dr.select(valid, dr.maximum(y1, fy), y1)
                vis |= valid
        f = M[2] / dr.norm(M[2])
        key = (dr.dot(geo.proxy - C, f) - geo.s.x * Kn.QUAD_SIGMA * dr.abs(dr.dot(geo.t_u, f))
               - geo.s.y * Kn.QUAD_SIGMA * dr.abs(dr.dot(geo.t_v, f)) - view.near)
        key = key - 1e-5 * dr.abs(key) - 1e-7 * view.near - 1e-6 * dr.norm(geo.proxy - C)
        dr.eval(x0, x1, y0, y1, vis, key)
    box = np.stack([np.array(x0), np.array(x1), np.array(y0), np.array(y1)], 1)
    return box.astype(np.float64), np.array(vis, bool), np.array(key, np.float64)


def bin_surfels(geo: SurfelGeometry, view: PinholeView) -> TileLists:
    """(tile, depth)-sorted entries of every kept surfel whose quad overlaps a tile.

    The depth key of a surfel is a lower bound on the ray distance t of any of its hits:
    the smallest camera depth z_lb = z_c − 3(s_u|t_u·f| + s_v|t_v·f|) of its proxy quad
    (f the viewing axis) minus the near-plane depth, since t = (z − near) / cos θ ≥ z − near
    for rays that start on the near plane, as Mitsuba's do.
    """
    box, vis, key_all = _project(geo, view)
    ox, oy = view.crop_offset
    W, H = view.crop_size
    ntx, nty = view.tiles
    ok = vis & geo.keep & np.all(np.isfinite(box), 1)
    px0 = np.floor(box[:, 0] - _MARGIN_PX) - ox
    px1 = np.floor(box[:, 1] + _MARGIN_PX) - ox
    py0 = np.floor(box[:, 2] - _MARGIN_PX) - oy
    py1 = np.floor(box[:, 3] + _MARGIN_PX) - oy
    ok &= (px1 >= 0) & (px0 <= W - 1) & (py1 >= 0) & (py0 <= H - 1)
    idx = np.nonzero(ok)[0]
    tx0 = (np.clip(px0[idx], 0, W - 1) // TILE).astype(np.int64)
    tx1 = (np.clip(px1[idx], 0, W - 1) // TILE).astype(np.int64)
    ty0 = (np.clip(py0[idx], 0, H - 1) // TILE).astype(np.int64)
    ty1 = (np.clip(py1[idx], 0, H - 1) // TILE).astype(np.int64)
    key = key_all[idx]
    order = np.argsort(key, kind="stable")                         # front to back
    idx, key = idx[order], key[order]
    tx0, tx1, ty0, ty1 = tx0[order], tx1[order], ty0[order], ty1[order]
    nx, ny = tx1 - tx0 + 1, ty1 - ty0 + 1
    counts = nx * ny                                               # [n] tiles per surfel
    total = int(counts.sum())
    first = np.repeat(np.cumsum(counts) - counts, counts)
    k = np.arange(total, dtype=np.int64) - first                   # index within its surfel
    nxr = np.repeat(nx, counts)
    tiles = (np.repeat(ty0, counts) + k // nxr) * ntx + np.repeat(tx0, counts) + k % nxr
    n_tiles = ntx * nty
    sort = np.argsort(tiles.astype(np.uint16 if n_tiles <= 1 << 16 else np.uint32),
                      kind="stable")                               # radix sort for 16 bit
    ids = np.repeat(idx, counts)[sort].astype(np.uint32)
    keys = np.repeat(key, counts)[sort].astype(np.float32)
    ebox = np.repeat(box[idx], counts, axis=0)[sort]                # [E, 4]
    ebox = (ebox + np.array([-_MARGIN_PX, _MARGIN_PX, -_MARGIN_PX, _MARGIN_PX])).astype(np.float32)
    per_tile = np.bincount(tiles, minlength=n_tiles)
    end = np.cumsum(per_tile)
    return TileLists(ids=to_jit(mi.UInt32, ids) if total else dr.zeros(mi.UInt32, 1),
                     keys=to_jit(mi.Float, keys) if total else dr.zeros(mi.Float, 1),
                     box=to_jit(mi.Vector4f, ebox.T) if total else dr.zeros(mi.Vector4f, 1),
                     start=to_jit(mi.UInt32, end - per_tile),
                     end=to_jit(mi.UInt32, end), entries=total)


def raster_hits(geo: SurfelGeometry, lists: TileLists, view: PinholeView, ray, pix, K: int,
                active=True) -> HitBuffer:
    """One walk (see :func:`_walk`): the first ≤ K hits of each ray; what lies behind the
    K-th is dropped. :func:`raster_all_hits` continues the walk until the ray is opaque."""
    return _walk(geo, lists, view, ray, pix, K, active)[0]


def raster_all_hits(geo: SurfelGeometry, lists: TileLists, view: PinholeView, ray, pix,
                    K: int, active=True, max_passes: int = MAX_PASSES):
    """Every hit of each ray up to transmittance ``T_MIN``, not only the first K.

    2DGS composites a tile's whole depth-sorted list until T < 1e-4; a fixed K-slot buffer
    instead drops whatever lies behind the K-th hit, adds the background with the
    transmittance left, and those surfels get no gradient. Here the walk is repeated for
    the rays whose buffer is full while still open (T ≥ ``T_MIN``), each pass collecting the
    next ≤ K hits strictly behind the previous pass's last one and continuing the product
    of (1 − α), up to ``max_passes`` passes (K · max_passes hits). Returns (HitBuffer with
    K · passes slots per ray, [R] bool: rays still open after the last pass).
    """
    R = dr.width(ray.d)
    hb, T, t_last = _walk(geo, lists, view, ray, pix, K, active)
    if lists.entries == 0:
        return hb, np.zeros(R, bool)
    ids = [np.asarray(hb.ids).reshape(R, K)]
    slots = [np.asarray(hb.slots).reshape(R, K)]
    count = np.asarray(hb.count).astype(np.int64)
    open_ = (np.asarray(hb.count) >= K) & (np.asarray(T) >= Kn.T_MIN)
    for _ in range(max_passes - 1):
        if not open_.any():
            break
        act = to_jit(mi.Bool, open_)
        h2, T2, t2 = _walk(geo, lists, view, ray, pix, K, act, t_after=t_last, T0=T)
        c2 = np.where(open_, np.asarray(h2.count), 0)
        ids.append(np.asarray(h2.ids).reshape(R, K))
        slots.append(np.asarray(h2.slots).reshape(R, K))
        count += c2
        T = dr.select(act, T2, T)
        t_last = dr.select(act, t2, t_last)
        open_ = open_ & (c2 >= K) & (np.asarray(T) >= Kn.T_MIN)
    P = len(ids)
    if P == 1:
        return hb, open_
    # rays closed in an earlier pass hold INVALID in later passes' slots: compact per ray
    all_ids = np.concatenate(ids, 1)                       # [R, P·K]
    all_slots = np.concatenate(slots, 1)
    return HitBuffer(ids=to_jit(mi.UInt32, all_ids.ravel()),
                     slots=to_jit(mi.UInt32, all_slots.ravel()),
                     count=to_jit(mi.UInt32, count.astype(np.uint32)), K=P * K), open_


def _walk(geo: SurfelGeometry, lists: TileLists, view: PinholeView, ray, pix, K: int,
          active=True, t_after=None, T0=None):
    """Hit buffer (≤ K hits per ray, ascending t) of rays through film pixels ``pix``.

    ``pix``: [R] integer film pixel (crop offset included) of each ray. The buffer holds
    what the tracer would find: the hits in t order up to the K-th or up to the one that
    takes Π(1 − α) below ``T_MIN``. As in the tracer, a hit is a hit of the ±3σ proxy
    quad (shifted along n by the proxy jitter) with α ≥ 1/255 of the analytic surfel, and
    t is the distance of the proxy, which orders coplanar surfels (``from_mesh`` faces)
    as the tracer does. Entries come in the order of a lower bound of their
    t, so the walk stops once that bound passes the cut t_cut (t of the last kept hit
    when the buffer is complete, else ∞); every new hit before t_cut is inserted by t
    and the cut is recomputed over the ≤ K sorted hits.

    ``t_after`` ([R] or None): only hits with t strictly greater count (a continued walk);
    ``T0`` ([R] or None): the transmittance in front of them. Returns (HitBuffer, [R]
    transmittance after the kept hits, [R] t of the last kept hit).
    """
    R = dr.width(ray.d)
    if lists.entries == 0:                          # nothing in view: no hits
        return (HitBuffer(ids=dr.full(mi.UInt32, INVALID, R * K), slots=dr.zeros(mi.UInt32, R * K),
                          count=dr.zeros(mi.UInt32, R), K=K),
                dr.full(mi.Float, 1.0, R) if T0 is None else mi.Float(T0), dr.zeros(mi.Float, R))
    with dr.suspend_grad():
        ray = mi.Ray3f(dr.detach(ray))
        ntx = view.tiles[0]
        tile = ((pix.y - view.crop_offset[1]) // TILE) * ntx + (pix.x - view.crop_offset[0]) // TILE
        j0 = dr.gather(mi.UInt32, lists.start, tile)
        j1 = dr.gather(mi.UInt32, lists.end, tile)
        j1 = dr.select(mi.Bool(active), j1, j0)
        pxf, pyf = mi.Float(pix.x), mi.Float(pix.y)
        t_lo = dr.full(mi.Float, -dr.inf, R) if t_after is None else mi.Float(t_after)
        T_in = dr.full(mi.Float, 1.0, R) if T0 is None else mi.Float(T0)
        tb = dr.alloc_local(mi.Float, K, mi.Float(dr.inf))
        ab = dr.alloc_local(mi.Float, K, mi.Float(0.0))
        ib = dr.alloc_local(mi.UInt32, K, mi.UInt32(INVALID))
        qmax = Kn.QUAD_SIGMA

        def cond(j, count, Tall, tcut, tb, ab, ib):
            key = dr.gather(mi.Float, lists.keys, j, j < j1)
            return (j < j1) & (key <= tcut)

        def test(m, j, tcut):
            """(hit, t, α, id) of entry j for pixels inside its film box (``m``)."""
            g = dr.gather(mi.UInt32, lists.ids, j, m)
            p = dr.gather(mi.Point3f, geo.p, g, m)
            c = dr.gather(mi.Point3f, geo.proxy, g, m)
            t_u = dr.gather(mi.Vector3f, geo.t_u, g, m)
            t_v = dr.gather(mi.Vector3f, geo.t_v, g, m)
            n = dr.gather(mi.Vector3f, geo.n, g, m)
            s = dr.gather(mi.Vector2f, geo.s, g, m)
            op = dr.gather(mi.Float, geo.op, g, m)
            t, u, v, ok = Kn.ray_surfel(ray.o, ray.d, c, t_u, t_v, n, s)       # proxy quad
            _, ua, va, oka = Kn.ray_surfel(ray.o, ray.d, p, t_u, t_v, n, s)    # the surfel
            alpha = Kn.surfel_alpha(op, ua, va)
            hit = (m & ok & oka & (dr.abs(u) <= qmax) & (dr.abs(v) <= qmax) & (t > 0)
                   & (t <= ray.maxt) & (t < tcut) & (t > t_lo) & (alpha >= Kn.ALPHA_MIN) & dr.isfinite(alpha)
                   & dr.isfinite(t))
            return hit, t, alpha, g

        def no_test(m, j, tcut):
            return mi.Bool(False), mi.Float(0.0), mi.Float(0.0), mi.UInt32(0)

        def insert(hit, t, alpha, g, count, Tall, tcut, tb, ab, ib):
            """Insert by t; when K hits are held or Π(1 − α) < T_MIN, cut the sorted list
            where the tracer would stop and set t_cut."""
            pos = dr.minimum(count, K - 1)

            def c2(pos, tb, ab, ib):
                return (pos > 0) & (tb[dr.maximum(pos, 1) - 1] > t)

            def b2(pos, tb, ab, ib):
                tb[pos] = tb[pos - 1]
                ab[pos] = ab[pos - 1]
                ib[pos] = ib[pos - 1]
                return pos - 1, tb, ab, ib

            pos, tb, ab, ib = dr.while_loop((pos, tb, ab, ib), c2, b2, label="raster insert")
            tb[pos], ab[pos], ib[pos] = t, alpha, g
            full = count == K                       # the last hit was dropped: rescan
            count = dr.minimum(count + 1, K)
            Tall = Tall * (1.0 - alpha)
            need = full | (Tall < Kn.T_MIN) | (count == K)

            def c3(k, T, L, tb, ab):
                return need & (k < count) & (L == K + 1)

            def b3(k, T, L, tb, ab):
                T = T * (1.0 - ab[k])
                L = dr.select(T < Kn.T_MIN, k + 1, L)
                return k + 1, T, L, tb, ab

            _, T, L, tb, ab = dr.while_loop((mi.UInt32(0), mi.Float(T_in), mi.UInt32(K + 1), tb, ab),
                                            c3, b3, label="raster cut")
            cut = need & ((L <= K) | (count == K))
            count = dr.select(need & (L <= K), L, count)
            Tall = dr.select(need, T, Tall)
            tcut = dr.select(cut, tb[dr.maximum(count, 1) - 1], tcut)
            return count, Tall, tcut, tb, ab, ib

        def no_insert(hit, t, alpha, g, count, Tall, tcut, tb, ab, ib):
            return count, Tall, tcut, tb, ab, ib

        def body(j, count, Tall, tcut, tb, ab, ib):
            # the pixel against the entry's film box first; symbolic conditionals skip the
            # surfel's data and the insertion for packets where no lane needs them
            b = dr.gather(mi.Vector4f, lists.box, j)
            m = (pxf + 1.0 >= b.x) & (pxf <= b.y) & (pyf + 1.0 >= b.z) & (pyf <= b.w)
            hit, t, alpha, g = dr.if_stmt((m, j, tcut), m, test, no_test, label="raster test")
            count, Tall, tcut, tb, ab, ib = dr.if_stmt(
                (hit, t, alpha, g, count, Tall, tcut, tb, ab, ib), hit, insert, no_insert,
                label="raster insert")
            return j + 1, count, Tall, tcut, tb, ab, ib

        j, count, Tall, tcut, tb, ab, ib = dr.while_loop(
            (mi.UInt32(j0), dr.zeros(mi.UInt32, R), mi.Float(T_in),
             dr.full(mi.Float, dr.inf, R), tb, ab, ib),
            cond, body, label="raster walk")
        t_last = dr.select(count > 0, tb[dr.maximum(count, 1) - 1], 0.0)
        base = dr.arange(mi.UInt32, R) * K
        ids = dr.full(mi.UInt32, INVALID, R * K)
        slots = dr.zeros(mi.UInt32, R * K)

        def c4(k, ib):
            return k < count

        def b4(k, ib):                                             # local → global index
            gi = ib[k]
            dr.scatter(ids, dr.gather(mi.UInt32, geo.local, gi), base + k)
            if geo.n_shapes > 1:
                dr.scatter(slots, dr.gather(mi.UInt32, geo.slot, gi), base + k)
            return k + 1, ib

        dr.while_loop((mi.UInt32(0), ib), c4, b4, label="raster write")
        dr.eval(ids, slots, count, Tall, t_last)
    return HitBuffer(ids=ids, slots=slots, count=count, K=K), Tall, t_last


def find_hits(shapes, sensor, ray, pix, K: int, active=True) -> HitBuffer:
    """Project, bin and walk once: the first ≤ K hits of ``sensor``'s rays ``ray`` through
    ``pix`` (what lies behind is dropped; :func:`find_all_hits` keeps it)."""
    view = pinhole_view(sensor)
    geo = surfel_geometry(shapes)
    return raster_hits(geo, bin_surfels(geo, view), view, ray, pix, K, active)


def find_all_hits(shapes, sensor, ray, pix, K: int, active=True, max_passes: int = MAX_PASSES):
    """Project, bin and walk until every ray is opaque (≤ ``max_passes`` walks of K hits):
    (HitBuffer, [R] bool rays still open), :func:`raster_all_hits`."""
    view = pinhole_view(sensor)
    geo = surfel_geometry(shapes)
    return raster_all_hits(geo, bin_surfels(geo, view), view, ray, pix, K, active, max_passes)
