"""Initial surfels for reconstruction step 1: from points, a visual hull, a box/sphere or a PLY."""
from __future__ import annotations

import warnings

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from comgs_dr.data.llff import view_near_far
from comgs_dr.data.types import project
from comgs_dr.surfels import load_ply
from comgs_dr.surfels.from_mesh import frame_to_quat
from comgs_dr.surfels.params import sh_from_base_colour
from comgs_dr.surfels.params import SurfelParams


def random_quaternions(n: int, rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


def nn_scale(points: np.ndarray, k: int = 3) -> np.ndarray:
    """3DGS scale init: RMS distance to the k nearest neighbours ([N])."""
    d, _ = cKDTree(points).query(points, k=k + 1)
    s = np.sqrt(np.mean(d[:, 1:] ** 2, axis=1))
    return np.maximum(s, 1e-7).astype(np.float32)


def pca_normal_quaternions(points: np.ndarray, k: int = 16, center=None) -> np.ndarray:
    """[N, 4] w-first quaternions whose surfel normal is the local PCA normal of ``points``
    (smallest-eigenvalue axis of the k nearest neighbours), oriented away from ``center``
    (default: the centroid). For a surface shell such as the visual hull's, this starts
    every surfel tangent to the surface instead of at a random orientation."""
    pts = np.asarray(points, np.float64)
    k = int(min(k, len(pts)))
    _, nb = cKDTree(pts).query(pts, k=k)
    q = pts[nb] - pts[nb].mean(1, keepdims=True)                       # [N, k, 3]
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))          # ascending eigenvalues
    n = vecs[:, :, 0]
    c = pts.mean(0) if center is None else np.asarray(center, np.float64)
    n *= np.where(((pts - c) * n).sum(1, keepdims=True) < 0, -1.0, 1.0)
    t = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    return frame_to_quat(np.stack([t, b, n], -1)).astype(np.float32)


def surfels_from_points(points: np.ndarray, colors: np.ndarray | None, rng: np.random.Generator,
                        sh_degree: int = 0, opacity: float = 0.1,
                        quats: np.ndarray | None = None) -> SurfelParams:
    """NN-based sizes, colour from ``colors`` (display values in [0,1]) or grey; random
    orientations unless ``quats`` [N, 4] are given."""
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4 or not np.all(np.isfinite(pts)):
        raise ValueError(f"surfels_from_points: need ≥ 4 finite points [N, 3], got {pts.shape}")
    n = len(pts)
    s = nn_scale(pts)
    k = (sh_degree + 1) ** 2
    sh = np.zeros((n, k, 3), np.float32)
    if colors is not None:
        sh[:, 0] = sh_from_base_colour(np.clip(np.asarray(colors, np.float32), 0, 1))[:, 0]
    return SurfelParams.from_numpy(
        means=pts, quats=random_quaternions(n, rng) if quats is None else quats,
        log_scales=np.log(np.c_[s, s]),
        opacity_logit=np.full(n, np.log(opacity / (1 - opacity)), np.float32), sh=sh)


def visual_hull_points(views, n: int, center: np.ndarray, radius: float, rng: np.random.Generator,
                       min_fraction: float = 0.95, max_tries: int = 60,
                       shell_px: float | None = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Space carving: uniform points in the bounding sphere kept where at least half of the
    views see them and they project inside the masks of ≥ ``min_fraction`` of those views;
    colour from one such view. With ``shell_px``, only points within that many pixels of
    a mask boundary in some view are kept: the hull's surface shell, where the object's
    surface is (interior points would be hidden surfels that only slow training).

    Returns (points [M, 3], colours [M, 3]); M ≤ n.
    """
    inner = None
    if shell_px is not None:
        inner = [None if v.mask is None else distance_transform_edt(v.mask > 0.5) for v in views]
    keep_p, keep_c = [], []
    total = 0
    box = None
    for _ in range(max_tries):
        if box is None:                           # first pass: the whole bounding sphere
            cand = random_sphere_points(4 * n, center, radius, rng)
        else:                                     # then the (10 % padded) box of what survived
            cand = rng.uniform(box[0], box[1], (4 * n, 3)).astype(np.float32)
        inside = np.zeros(len(cand), np.int32)
        seen = np.zeros(len(cand), np.int32)
        color = np.full((len(cand), 3), 0.5, np.float32)
        depth_px = np.full(len(cand), np.inf)
        for j, v in enumerate(views):
            px, py, ok = project(v.camera, cand)
            if v.mask is None:
                continue
            h, w = v.mask.shape
            xi = np.clip(px.astype(int), 0, w - 1)
            yi = np.clip(py.astype(int), 0, h - 1)
            m = ok & (v.mask[yi, xi] > 0.5)
            seen += ok
            inside += m
            color[m] = v.image[yi[m], xi[m]]
            if inner is not None and inner[j] is not None:
                depth_px = np.where(ok, np.minimum(depth_px, inner[j][yi, xi]), depth_px)
        # Seen by at least half of the views: a point just in front of one camera lands
        # inside that camera's mask but is a floater, not part of the object.
        good = (seen >= max(1, 0.5 * len(views))) & (inside >= min_fraction * seen)
        if inner is not None:
            good &= depth_px <= shell_px
        keep_p.append(cand[good])
        keep_c.append(color[good])
        total += int(good.sum())
        if total >= n:
            break
        if total >= 32:
            allp = np.concatenate(keep_p)
            lo, hi = allp.min(0), allp.max(0)
            box = (lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo))
    pts = np.concatenate(keep_p)[:n]
    cols = np.concatenate(keep_c)[:n]
    if len(pts) < 4:
        raise ValueError("visual hull initialisation found no points inside the masks; check the "
                         "masks and cameras, or initialise from random points")
    return pts.astype(np.float32), cols




def pixel_rays(camera, x, y) -> tuple[np.ndarray, np.ndarray]:
    """World rays through film positions (x, y) [M] of a pinhole :class:`Camera` (the inverse
    of :func:`comgs_dr.data.types.project`): origin [3] and directions [M, 3] whose camera-space
    z is 1 (so ``o + z·d`` is the point at z-depth z)."""
    w, h = camera.width, camera.height
    f = 0.5 * w / np.tan(np.radians(camera.fov_x_deg) / 2)
    cx = w * (0.5 - getattr(camera, "principal_point_offset_x", 0.0))
    cy = h * (0.5 - getattr(camera, "principal_point_offset_y", 0.0))
    T = np.asarray(camera.to_world, np.float64)
    pc = np.stack([(cx - np.asarray(x)) / f, (cy - np.asarray(y)) / f, np.ones(np.size(x))], 1)
    return T[:3, 3], pc @ T[:3, :3].T


def hull_ray_points(views, n: int, center: np.ndarray, radius: float, rng: np.random.Generator,
                    depths: int = 64, source_alpha: float = 0.25, carve_alpha: float = 0.1,
                    min_fraction: float = 0.95, max_tries: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Visual-hull surface points found from the images: for random object pixels of random
    views, the first of ``depths`` stratified points along the pixel's ray (inside the
    bounding sphere) that projects inside the masks of ≥ ``min_fraction`` of the views that
    see it (seen by at least half of them); its colour is the pixel's.

    Points land on the hull in proportion to the image area the object covers, so thin
    structures get their share: uniform samples in the volume (:func:`visual_hull_points`)
    almost never fall inside a rod one pixel wide, which then never gets surfels. Sub-pixel structures have
    alpha below 0.5, so a pixel is an object pixel at alpha > ``source_alpha`` and carving
    tests the 3×3 maximum of the alpha against ``carve_alpha`` (one pixel of tolerance).

    Returns (points [M, 3], colours [M, 3]); M ≤ n.
    """
    from scipy.ndimage import maximum_filter

    views = [v for v in views if v.mask is not None]
    if not views:
        raise ValueError("hull_ray_points: no view has a mask")
    carve = [maximum_filter(v.mask, size=3) > carve_alpha for v in views]
    pix = [np.flatnonzero(v.mask.ravel() > source_alpha) for v in views]
    if sum(len(p) for p in pix) == 0:
        raise ValueError("visual hull initialisation: every mask is empty (alpha ≤ "
                         f"{source_alpha}); check the masks, or initialise from random points")
    center = np.asarray(center, np.float64)
    keep_p, keep_c, total = [], [], 0
    for _ in range(max_tries):
        for j in rng.permutation(len(views)):
            if total >= n:
                break
            if not len(pix[j]):
                continue
            v, m = views[j], -(-n // len(views))                        # rays from this view
            cam = v.camera
            w = cam.width
            flat = rng.choice(pix[j], m)
            x, y = flat % w + rng.uniform(0, 1, m), flat // w + rng.uniform(0, 1, m)
            o, d = pixel_rays(cam, x, y)
            d /= np.linalg.norm(d, axis=1, keepdims=True)                  # [m, 3]
            b = d @ (o - center)                                          # ray–sphere
            disc = b * b - (np.sum((o - center) ** 2) - radius * radius)
            hit = disc > 0
            t0 = np.maximum(-b - np.sqrt(np.maximum(disc, 0)), 0)
            t1 = -b + np.sqrt(np.maximum(disc, 0))
            t = t0[:, None] + (np.arange(depths) + rng.uniform(0, 1, (m, depths))) / depths \
                * (t1 - t0)[:, None]                                      # [m, D]
            cand = (o + d[:, None, :] * t[..., None]).reshape(-1, 3)     # [m·D, 3]
            inside = np.zeros(len(cand), np.int32)
            seen = np.zeros(len(cand), np.int32)
            for k, u in enumerate(views):
                px, py, ok = project(u.camera, cand)
                xi = np.clip(px.astype(int), 0, u.camera.width - 1)
                yi = np.clip(py.astype(int), 0, u.camera.height - 1)
                seen += ok
                inside += ok & carve[k][yi, xi]
            good = ((seen >= max(1, 0.5 * len(views))) & (inside >= min_fraction * seen)) \
                .reshape(m, depths) & hit[:, None]
            ray_ok = good.any(1)
            first = good.argmax(1)
            pts = o + d * t[np.arange(m), first][:, None]
            keep_p.append(pts[ray_ok])
            keep_c.append(v.image[(flat // w)[ray_ok], (flat % w)[ray_ok], :3])
            total += int(ray_ok.sum())
        if total >= n:
            break
    pts = np.concatenate(keep_p)[:n] if keep_p else np.zeros((0, 3))
    if len(pts) < 4:
        raise ValueError("visual hull initialisation found no points inside the masks; check the "
                         "masks and cameras, or initialise from random points")
    return pts.astype(np.float32), np.concatenate(keep_c)[:n].astype(np.float32)


def frustum_points(views, n: int, center, radius: float, rng: np.random.Generator,
                   min_seen: float = 0.5, max_tries: int = 40) -> np.ndarray:
    """Uniform points in the bounding sphere that at least ``min_seen`` of the views see
    (the common view frustum): a random initialisation without masks or SfM points.

    The bounding sphere encloses the cameras; filling all of it puts most surfels beside or
    right in front of the cameras, where they occlude every view they are in and get pruned
    only slowly.
    Returns [M, 3] float32 with M = n, or fewer if the frustum is tiny (at least 4, else an error).
    """
    keep, total = [], 0
    for _ in range(max_tries):
        cand = random_sphere_points(4 * n, center, radius, rng)
        seen = np.zeros(len(cand), np.int32)
        for v in views:
            seen += project(v.camera, cand)[2]
        good = cand[seen >= max(1, min_seen * len(views))]
        keep.append(good)
        total += len(good)
        if total >= n:
            break
    pts = np.concatenate(keep)[:n]
    if len(pts) < 4:
        raise ValueError(f"random initialisation: no point of the bounding sphere is seen by "
                         f"{min_seen:.0%} of the {len(views)} training views; check the camera poses")
    return pts.astype(np.float32)


def random_sphere_points(n: int, center, radius: float, rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return (np.asarray(center) + d * radius * rng.uniform(0, 1, (n, 1)) ** (1 / 3)).astype(np.float32)


def normal_quaternions(normals) -> np.ndarray:
    """[N, 4] w-first quaternions of surfels whose normal (local +Z) is ``normals`` [N, 3]
    (need not be unit length); the tangent axes are arbitrary but deterministic."""
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    t = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return frame_to_quat(np.stack([t, np.cross(n, t), n], -1)).astype(np.float32)


#: ``RadianceConfig.init_sweep_points=None``: plane-swept points added to a scene's sparse
#: SfM points (at most up to ``init_points``). On a 20-photo phone capture (1485 SfM points,
#: 250 px) 4000 took the held-out PSNR from 17.8 to about 23 dB at ~5x the cost per
#: iteration; 18500 fitted the training views no better at ~3x the cost of 4000.
SWEEP_FILL = 4000
#: ... only when the points are that sparse: fewer than this many per training pixel (SfM
#: of real photos: 0.0005-0.003; synthetic scenes with their points3d.ply, whose sky a
#: fill at 24 px cannot tell from the far field: 0.1). Not 0.01: the default demo's scene
#: (0.0075) was filled, and the fill's leftover floaters shade the ground toward the sun:
#: the shadows toward its seen sun fell from z 14.1 to 2.9 (14 % of the ground "shadowed"),
#: its power was left to the light head, the composite's shadow depth fell 0.70 -> 0.32 and
#: SOP beat the paste on 2 of 4 frames (docs/composite.md)
SWEEP_SPARSE_PER_PIXEL = 0.005


def points_near_far(views, points, percentiles=(1.0, 99.0), margin=(0.67, 1.2),
                    min_points: int = 8) -> np.ndarray | None:
    """[N, 2] (near, far) z-depths of ``views`` from the sparse ``points`` [P, 3] each one
    sees (in front, inside the image): the ``percentiles`` of their depths widened by
    ``margin``, as LLFF's ``imgs2poses`` derives its bounds from the COLMAP points. A view
    seeing fewer than ``min_points`` points takes the median bounds of the others; None
    when no view sees enough."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    nf = np.full((len(views), 2), np.nan)
    for j, v in enumerate(views):
        _, _, ok = project(v.camera, pts)
        m = np.linalg.inv(np.asarray(v.camera.to_world, np.float64))
        z = (pts @ m[:3, :3].T + m[:3, 3])[:, 2]
        z = z[ok & (z > 0)]
        if len(z) >= min_points:
            lo, hi = np.percentile(z, percentiles)
            nf[j] = lo * margin[0], hi * margin[1]
    good = np.isfinite(nf).all(1) & (nf[:, 0] > 0) & (nf[:, 1] > nf[:, 0])
    if not good.any():
        return None
    nf[~good] = np.median(nf[good], axis=0)
    return nf


def sweep_fill_points(data, n: int, rng: np.random.Generator, far_field: bool):
    """``n`` plane-swept points (:func:`near_far_points`, 32 disparities, 8 neighbours) of
    the training views between the near/far bounds their SfM points give
    (:func:`points_near_far`): dense surface samples where the sparse points are few, e.g.
    low-texture walls and bedding a phone capture's SIFT leaves almost empty. Returns
    (points, colours, normals) or None without usable bounds."""
    nf = points_near_far(data.train, data.points)
    if nf is None or n < 4 or len(data.train) < 2:
        return None
    return near_far_points(data.train, nf, n, rng, candidates=32, neighbours=8,
                           far_field=far_field)


FAR_FIELD_DEPTH = 1e4      # × far: the "at infinity" candidate of ``far_field``
FAR_FIELD_TOL = (1.25, 0.005)   # far field: cost at infinity ≤ a·best finite cost + b


def near_far_points(views, near_far, n: int, rng: np.random.Generator, candidates: int = 1,
                    neighbours: int = 4, far_field: bool = False):
    """Random points in the union of the training frusta between each view's near/far
    bounds: the initialisation of forward-facing captures (LLFF) without SfM points.

    Each point comes from one view (round robin over ``views``): a uniformly random pixel,
    back-projected to a depth drawn uniformly in inverse depth (disparity) between that
    view's ``near_far[i] = (near, far)`` z-depths, as NDC/forward-facing methods sample, so
    near content gets as many points per depth layer as the background. Its colour is that
    pixel's (the view's stored image value) and its normal points back along the view ray
    (a forward-facing scene is seen from one side).

    ``candidates`` > 1: a crude plane sweep instead of one random depth. The point gets
    the most photo-consistent of ``candidates`` stratified disparities: the 3x3 patch
    around its pixel against the patches its candidate positions project to in the
    ``neighbours`` nearest training views (mean absolute colour difference, averaged over
    the better half of the neighbours that see it, so one occluding view does not veto
    the right depth). Where no neighbour sees any candidate the depth stays random.

    ``far_field`` (with ``candidates`` > 1): one more candidate ``FAR_FIELD_DEPTH`` × far away,
    i.e. at infinity; a pixel whose patch matches there about as well as at its best finite
    depth (``FAR_FIELD_TOL``) shows no parallax — the sky, or a distant low-texture wall — and
    its point is dropped, left to a learned background (``reconstruct --background env``,
    ``RadianceConfig.init_far_field``). A pixel no neighbour sees at any finite depth is kept.
    Why: otherwise every pixel gets a point between near and far, so a forward-facing
    capture's sky is held by surfels at the far bound, the background learns almost
    nothing, and from a placement in the scene those surfels hang overhead as a clipped
    white ceiling.

    Returns (points [n', 3] float32, colours [n', 3] float32, normals [n', 3] float32 unit),
    n' = n, or n minus the far-field pixels.
    """
    nf = np.asarray(near_far, np.float64).reshape(-1, 2)
    if len(nf) != len(views):
        raise ValueError(f"near_far_points: {len(nf)} near/far pairs for {len(views)} views")
    if not (np.isfinite(nf).all() and (nf[:, 0] > 0).all() and (nf[:, 1] > nf[:, 0]).all()):
        raise ValueError("near_far_points: need 0 < near < far (finite) for every view")
    if n < 4:
        raise ValueError(f"near_far_points: need n >= 4 points, got {n}")
    k = max(int(candidates), 1)
    far_field = bool(far_field) and k > 1 and len(views) > 1
    keep = np.ones(n, bool)
    centers = np.array([np.asarray(v.camera.to_world, np.float64)[:3, 3] for v in views])
    owner = np.arange(n) % len(views)
    pts = np.empty((n, 3))
    cols = np.empty((n, 3), np.float32)
    nrm = np.empty((n, 3))
    for j, v in enumerate(views):
        idx = np.flatnonzero(owner == j)
        if not len(idx):
            continue
        m_ = len(idx)
        cam = v.camera
        w, h = cam.width, cam.height
        ix, iy = rng.integers(0, w, m_), rng.integers(0, h, m_)
        # random position in the pixel; its centre when matching (the reference patch's)
        jit = rng.uniform(0, 1, (m_, 2)) if k == 1 else np.full((m_, 2), 0.5)
        x, y = ix + jit[:, 0], iy + jit[:, 1]
        near, far = nf[j]
        # k stratified disparities per point (k = 1: uniform in [1/far, 1/near])
        s = 1.0 / far + (np.arange(k) + rng.uniform(0, 1, (m_, k))) / k * (1.0 / near - 1.0 / far)
        z = 1.0 / s                                                        # [m, k]
        o, d = pixel_rays(cam, x, y)                                       # |d_z| = 1 in camera
        if k > 1 and len(views) > 1:
            nb = np.argsort(np.linalg.norm(centers - centers[j], axis=1))[1:1 + int(neighbours)]
            zc = np.concatenate([z, np.full((m_, 1), FAR_FIELD_DEPTH * far)], 1) if far_field \
                else z                                                     # [m, k (+1)]
            cand = o + d[:, None, :] * zc[..., None]               # [m, k (+1), 3]
            others = [views[i] for i in nb]
            total, best = [], []
            for c in range(0, m_, 2048):                                   # bounded memory
                t_ = _photo_costs(v.image, ix[c:c + 2048], iy[c:c + 2048], cand[c:c + 2048],
                                  others)                                  # [≤2048, k (+1)]
                total.append(t_)
                best.append(_best(t_[:, :k], rng))
            total, best = np.concatenate(total), np.concatenate(best)
            if far_field:
                fin = total[np.arange(m_), best]
                a, b = FAR_FIELD_TOL
                keep[idx] = ~(np.isfinite(fin) & np.isfinite(total[:, k])
                              & (total[:, k] <= a * fin + b))
            z = z[np.arange(m_), best]
        else:
            z = z[:, 0]
        pts[idx] = o + d * z[:, None]
        nrm[idx] = -d / np.linalg.norm(d, axis=1, keepdims=True)
        cols[idx] = v.image[iy, ix, :3]
    return pts[keep].astype(np.float32), cols[keep], nrm[keep].astype(np.float32)


def _best(total, rng) -> np.ndarray:
    """[m] index of the lowest cost per row of ``total`` [m, k]; random where none is finite
    (no neighbour sees any candidate)."""
    best = np.argmin(total, axis=1)
    none = ~np.isfinite(total).any(1)
    best[none] = rng.integers(0, total.shape[1], int(none.sum()))
    return best


def _photo_costs(image, ix, iy, cand, others) -> np.ndarray:
    """[m, k] photo-consistency cost of each candidate in ``cand`` [m, k, 3]: how well its
    3x3 patches in ``others`` match the reference patch around pixel (ix, iy) of ``image``
    (see near_far_points; inf where no neighbour sees it). Neighbour patches are sampled
    bilinearly around the candidate's sub-pixel projection."""
    m_, k = cand.shape[:2]
    off = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], np.float64)  # [9, 2]
    h, w = image.shape[:2]
    ref = image[np.clip(iy[:, None] + off[:, 0].astype(int), 0, h - 1),
                np.clip(ix[:, None] + off[:, 1].astype(int), 0, w - 1), :3]         # [m, 9, 3]
    costs = np.full((len(others), m_, k), np.inf)
    for o, v in enumerate(others):
        px, py, ok = project(v.camera, cand.reshape(-1, 3))
        patch = _bilinear(v.image, px.reshape(m_, k, 1) + off[:, 1], py.reshape(m_, k, 1) + off[:, 0])
        c = np.abs(patch - ref[:, None]).mean((2, 3))                               # [m, k]
        costs[o] = np.where(ok.reshape(m_, k), c, np.inf)
    costs.sort(axis=0)                                                      # best neighbours first
    half = max(1, (len(others) + 1) // 2)
    seen = np.isfinite(costs[:half]).sum(0)                                 # [m, k]
    return np.where(seen > 0, np.where(np.isfinite(costs[:half]), costs[:half], 0).sum(0)
                    / np.maximum(seen, 1), np.inf)


def _bilinear(image, x, y) -> np.ndarray:
    """``image`` [H, W, C] at continuous pixel coordinates (pixel centres at i + 0.5),
    edge-clamped; x, y of any equal shape S -> [*S, 3]."""
    h, w = image.shape[:2]
    x = np.clip(x - 0.5, 0, w - 1)
    y = np.clip(y - 0.5, 0, h - 1)
    x0 = np.minimum(x.astype(int), w - 2) if w > 1 else np.zeros_like(x, int)
    y0 = np.minimum(y.astype(int), h - 2) if h > 1 else np.zeros_like(y, int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    im = image[..., :3]
    return (im[y0, x0] * (1 - fx) + im[y0, x1] * fx) * (1 - fy) + \
        (im[y1, x0] * (1 - fx) + im[y1, x1] * fx) * fy


def initial_surfels(data, cfg, rng) -> tuple[SurfelParams, str]:
    """Initial surfels of step 1 (``cfg``: a ``RadianceConfig``) and a description of where
    they came from.

    ``init="auto"``: the visual-hull shell (object preset with masks), else the dataset's
    points, else — when the poses carry near/far bounds (LLFF ``poses_bounds.npy``) —
    ``"nearfar"``: one point per random training pixel, at the most photo-consistent (8
    nearest views) of 32 depths stratified in disparity between that view's bounds,
    coloured by its pixel, facing its camera, at ``init_opacity`` like SfM points
    (:func:`comgs_dr.train.init.near_far_points`); else ``"random"`` points in the common
    view frustum. The scene preset warns when it has no points, naming the init used.
    The near/far plane sweep starts a forward-facing capture close to what its true depths
    would give, well ahead of random depths.
    """
    center, radius = data.bounds
    how = cfg.init
    has_masks = all(v.mask is not None for v in data.train)
    near_far = view_near_far(data, data.train)
    if how == "auto":
        how = "hull" if (cfg.preset == "object" and has_masks) else (
            "points" if data.points is not None and len(data.points) >= 4 else
            "nearfar" if near_far is not None else "random")
    if how == "hull":
        pts, cols = hull_ray_points(data.train, cfg.init_points, np.asarray(center), radius, rng)
        quats = pca_normal_quaternions(pts) if cfg.init_normals else None
        return surfels_from_points(pts, cols, rng, opacity=cfg.init_opacity, quats=quats), \
            f"visual-hull surface from the pixels' rays ({len(pts)} points" \
            f"{', PCA normals' if quats is not None else ''})"
    if how == "points":
        if data.points is None:
            raise ValueError("init='points' but the dataset has no points (use hull or random)")
        quats = pca_normal_quaternions(data.points) if cfg.init_normals else None
        desc = f"dataset points ({len(data.points)}{', PCA normals' if quats is not None else ''})"
        fill = getattr(cfg, "init_sweep_points", 0)
        if fill is None:                # the scene preset's sparse SfM points get a fill
            pixels = sum(v.camera.width * v.camera.height for v in data.train)
            sparse = len(data.points) < SWEEP_SPARSE_PER_PIXEL * pixels
            fill = min(SWEEP_FILL, max(cfg.init_points - len(data.points), 0)) \
                if cfg.preset == "scene" and sparse else 0
        swept = sweep_fill_points(data, int(fill), rng, far_field=cfg.background == "env"
                                  and cfg.init_far_field) if fill else None
        if swept is not None and len(swept[0]):
            sp, sc, sn = swept
            cols = data.colors if data.colors is not None else \
                np.full((len(data.points), 3), 0.5, np.float32)
            q0 = quats if quats is not None else random_quaternions(len(data.points), rng)
            desc += (f" + {len(sp)} plane-swept points between the near/far depths of each "
                     f"view's SfM points")
            return surfels_from_points(np.concatenate([data.points, sp]),
                                       np.concatenate([cols, sc]), rng, opacity=cfg.init_opacity,
                                       quats=np.concatenate([q0, normal_quaternions(sn)])), desc
        return surfels_from_points(data.points, data.colors, rng, opacity=cfg.init_opacity,
                                     quats=quats), desc
    if how == "nearfar":
        if near_far is None:
            raise ValueError("init='nearfar' needs per-view near/far bounds (LLFF poses_bounds.npy); "
                             "this dataset has none (use random or points)")
        far = cfg.background == "env" and cfg.init_far_field
        pts, cols, normals = near_far_points(data.train, near_far, cfg.init_points, rng,
                                               candidates=32, neighbours=8, far_field=far)
        if len(pts) < 4:                 # all sky: keep the sweep's points after all
            pts, cols, normals = near_far_points(data.train, near_far, cfg.init_points, rng,
                                                   candidates=32, neighbours=8)
            far = False
        dropped = (f", {cfg.init_points - len(pts)} pixels matching as well at infinity left "
                   f"to the learned background" if far else "")
        desc = (f"near/far frusta ({len(pts)} pixels swept over 32 disparities between the poses' "
                f"bounds {near_far[:, 0].min():.3g}–{near_far[:, 1].max():.3g}, most photo-consistent "
                f"depth, pixel colours, camera-facing{dropped})")
        if cfg.preset == "scene" and data.points is None:
            warnings.warn(f"scene preset without dataset points: initialised from the {desc}; "
                          "SfM points (COLMAP, or a points3d.ply) give a better start", stacklevel=3)
        return surfels_from_points(pts, cols, rng, opacity=cfg.init_opacity,
                                     quats=normal_quaternions(normals)), desc
    if how == "random":
        if cfg.preset == "scene":
            why = ("without dataset points or near/far bounds" if near_far is None else
                   "with init='random' (the poses' near/far bounds are not used)")
            warnings.warn(f"scene preset {why}: random initialisation in the common view frustum "
                          "(grey, random orientations), measured at 14.1 dB test PSNR on `comgs "
                          "make-dataset scene --points 0` (30.6 dB with points); give COLMAP points "
                          "or a points3d.ply", stacklevel=3)
        pts = frustum_points(data.train, cfg.init_points, np.asarray(center), radius, rng)
        return surfels_from_points(pts, None, rng), f"random, in the common view frustum ({len(pts)} points)"
    if str(how).endswith(".ply"):
        return load_ply(how), f"PLY {how}"
    raise ValueError(f"unknown init {cfg.init!r}: auto, hull, points, nearfar, random or a .ply path")
