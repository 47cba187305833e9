"""Layered G-buffers of several surfel shapes traced together (composition).

One camera ray is traced through *all* surfel shapes of a scene (a reconstructed scene and
the objects placed in it), and the front-to-back weights w_k = T_k α_k (paper eq.
Multi-Target Rendering) of its hits are accumulated per *group* of shapes: per group g the
coverage W_g = Σ_{k∈g} w_k, unbiased depth D_g/W_g, normal and (optionally) radiance-field
colour. A surfel of one group hides what lies behind it in every group, so depth
compositing is exact per surfel and antialiased (Σ_g W_g ≤ 1 at an object's silhouette
splits the pixel between the object and what is behind it), instead of a per-pixel depth
test of separately rendered layers.

The per-hit weights (surfel id, shape slot, w) are kept so that a group's material buffers
can be blended later as a differentiable gather (:func:`group_materials`), as
``shading.deferred`` does for one shape.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from comgs_dr.core.cameras import camera_rays
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.octahedral import expand_mode
from comgs_dr.surfels import composite
from comgs_dr.surfels.composite import trace_composite
from comgs_dr.surfels.kernel import clamp_closed


DEPTH_STEP_TOL = 0.1      # a neighbour deeper or shallower by more than this × depth: an edge


@dataclass
class GroupBuffers:
    """Per-pixel layers [H*W] of each group, plus the per-hit blend weights [H*W*K]."""
    shape: tuple                 # (H, W)
    origins: mi.Point3f          # [H*W]
    dirs: mi.Vector3f            # [H*W] unit
    weight: list                 # G × mi.Float      W_g
    depth: list                  # G × mi.Float      unbiased depth (0 where W_g = 0)
    normal: list                 # G × mi.Vector3f   unit (0 where W_g = 0), facing the camera
    colour: dict                 # g -> mi.Color3f  premultiplied radiance-field colour
    ids: mi.UInt32               # [H*W*K] surfel index of hit k
    slots: mi.UInt32             # [H*W*K] shape slot of hit k
    w: mi.Float                  # [H*W*K] T_k α_k (0 for unused slots)
    K: int

    def points(self, g: int, pix):
        """(x [P], n [P]) shading points of group ``g`` at pixels ``pix`` (mi.UInt32)."""
        o = dr.gather(mi.Point3f, self.origins, pix)
        d = dr.gather(mi.Vector3f, self.dirs, pix)
        x = mi.Point3f(o + d * dr.gather(mi.Float, self.depth[g], pix))
        return x, dr.gather(mi.Vector3f, self.normal[g], pix), mi.Vector3f(-d)

    def depth_normals(self, g: int, rel_tol: float = DEPTH_STEP_TOL,
                      min_weight: float = 1e-3, radius: int = 2) -> tuple:
        """(n [H*W], valid [H*W]): the normal of group ``g``'s depth layer, from the
        positions of each pixel's horizontal and vertical neighbours (central differences,
        one-sided at a depth step larger than ``rel_tol`` × depth or an uncovered
        neighbour), turned to the side of the surfels' own normal and averaged over the
        (2·``radius`` + 1)² pixels around it on the same surface (depth within ``rel_tol``).
        ``valid`` is False where a pixel has no usable neighbour on an axis; there the
        surfels' normal is returned.

        Why: the surfels' normals of a briefly trained scene scatter about the surface, and
        the shadow ratio weights the light by their cosine to it, so the sun's shadow would
        come out patchy and light; the rendered depth of the same surfels is smooth."""
        h, w = self.shape
        idx = dr.arange(mi.UInt32, h * w)
        row, col = idx // w, idx % w
        x, n, _ = self.points(g, idx)
        D = self.depth[g]
        ok = (self.weight[g] > min_weight) & (D > 0)

        def neighbour(j_ok, j):             # (its point, usable: covered, same surface)
            j = dr.select(j_ok, j, idx)
            use = j_ok & dr.gather(mi.Bool, ok, j) \
                & (dr.abs(dr.gather(mi.Float, D, j) - D) <= rel_tol * D)
            return dr.select(use, dr.gather(mi.Point3f, x, j), x), use

        def axis(step, lo_ok, hi_ok):
            lo, a_ok = neighbour(lo_ok, idx - step)
            hi, b_ok = neighbour(hi_ok, idx + step)
            return mi.Vector3f(hi - lo), a_ok | b_ok

        tx, ok_x = axis(1, col > 0, col + 1 < w)
        ty, ok_y = axis(w, row > 0, row + 1 < h)
        c = dr.cross(tx, ty)
        norm = dr.norm(c)
        valid = ok & ok_x & ok_y & (norm > 0)
        nd = c / dr.maximum(norm, 1e-30)
        nd = dr.select(dr.dot(nd, n) < 0, -nd, nd)
        if radius > 0:          # mean over the (2r+1)² pixels on the same surface
            acc = dr.zeros(mi.Vector3f, h * w)
            for dy in range(-radius, radius + 1):
                for dx in range(-radius, radius + 1):
                    r2, c2 = mi.Int32(row) + dy, mi.Int32(col) + dx
                    inside = (r2 >= 0) & (r2 < h) & (c2 >= 0) & (c2 < w)
                    j = dr.select(inside, mi.UInt32(r2 * w + c2), idx)
                    same = inside & dr.gather(mi.Bool, valid, j) \
                        & (dr.abs(dr.gather(mi.Float, D, j) - D) <= rel_tol * D)
                    acc += dr.select(same, dr.gather(mi.Vector3f, nd, j), 0.0)
            m = dr.norm(acc)
            nd = dr.select(m > 0, acc / dr.maximum(m, 1e-30), nd)
        return mi.Vector3f(dr.select(valid, nd, n)), valid


def group_gbuffer(scene, sensor, group_of_shape: list[int] | dict[str, int], K: int = 32,
                  colour_groups=()) -> GroupBuffers:
    """Layers of ``sensor``'s pixels (no AD). ``group_of_shape``: {shape id: group}, or a
    list whose j-th entry is the group of the j-th shape of ``composite.surfel_shapes`` (sorted
    by id); groups are 0..G−1. ``colour_groups``: groups whose radiance-field colour is
    accumulated (SH evaluated only for those hits)."""
    shapes = composite.surfel_shapes(scene, "group_gbuffer")
    if isinstance(group_of_shape, dict):
        ids = [s.id() for s in shapes]
        if set(group_of_shape) != set(ids):
            raise ValueError(f"group_gbuffer: groups given for {sorted(group_of_shape)} but the "
                             f"scene's surfels shapes are {ids}")
        group_of_shape = [group_of_shape[i] for i in ids]
    if len(group_of_shape) != len(shapes):
        raise ValueError(f"group_gbuffer: {len(shapes)} surfels shapes but "
                         f"{len(group_of_shape)} group entries")
    G = max(group_of_shape) + 1
    colour_groups = tuple(sorted(set(colour_groups)))
    with dr.suspend_grad():
        dirs, origins = camera_rays(sensor)
        h, w = dirs.shape[:2]
        ray = mi.Ray3f(mi.Point3f(dr.unravel(mi.Point3f, origins.array)),
                       mi.Vector3f(dr.unravel(mi.Vector3f, dirs.array)))
        eps = composite.auto_epsilon(scene, shapes)
        hits, _, _, _ = trace_composite(scene, shapes, ray, K, eps, ("weight",))
        R = h * w
        rid = dr.arange(mi.UInt32, R)
        group_lut = to_jit(mi.UInt32, group_of_shape)
        wts = dr.zeros(mi.Float, R * K)
        names = ("weight", "depth", "normal") + (("color",) if colour_groups else ())

        def body(k, T, acc):
            pos = rid * K + k
            active = k < hits.count
            index = dr.gather(mi.UInt32, hits.ids, pos, active)
            slot = dr.gather(mi.UInt32, hits.slots, pos, active) if len(shapes) > 1 \
                else mi.UInt32(0)
            smp, vals = composite.surfel_values(shapes, slot, index, ray, active, names)
            wk = dr.select(active, T * smp.alpha, 0.0)                      # T_k α_k
            dr.scatter(wts, wk, pos, active)
            grp = dr.gather(mi.UInt32, group_lut, slot)
            new = {}
            for g in range(G):
                wg = dr.select(grp == g, wk, 0.0)
                new[f"W{g}"] = acc[f"W{g}"] + wg
                new[f"D{g}"] = dr.fma(smp.t, wg, acc[f"D{g}"])
                new[f"N{g}"] = dr.fma(smp.normal, wg, acc[f"N{g}"])
                if g in colour_groups:
                    new[f"C{g}"] = dr.fma(vals["color"], wg, acc[f"C{g}"])
            return k + 1, T * (1.0 - smp.alpha), new

        acc0 = {}
        for g in range(G):
            acc0[f"W{g}"] = dr.zeros(mi.Float, R)
            acc0[f"D{g}"] = dr.zeros(mi.Float, R)
            acc0[f"N{g}"] = dr.zeros(mi.Vector3f, R)
            if g in colour_groups:
                acc0[f"C{g}"] = dr.zeros(mi.Color3f, R)
        _, _, acc = dr.while_loop((mi.UInt32(0), dr.full(mi.Float, 1.0, R), acc0),
                                  lambda k, T, a: k < hits.count, body, label="group layers")
        weight, depth, normal = [], [], []
        for g in range(G):
            Wg = acc[f"W{g}"]
            ok = Wg > 1e-6
            inv = dr.rcp(dr.maximum(Wg, 1e-6))
            weight.append(Wg)
            depth.append(dr.select(ok, acc[f"D{g}"] * inv, 0.0))
            n = acc[f"N{g}"]
            nn = dr.norm(n)
            normal.append(dr.select(ok & (nn > 1e-8), n / dr.maximum(nn, 1e-8), 0.0))
        colour = {g: acc[f"C{g}"] for g in colour_groups}
        dr.eval(weight, depth, normal, colour, wts)
    return GroupBuffers(shape=(h, w), origins=ray.o, dirs=ray.d, weight=weight, depth=depth,
                        normal=normal, colour=colour, ids=hits.ids, slots=hits.slots, w=wts,
                        K=K)


def group_materials(buf: GroupBuffers, pix, slot: int, params) -> dict:
    """Albedo/roughness/metallic [P] of shape ``slot`` at pixels ``pix``: the blend
    Σ_k w_k b_{i_k} / Σ_k w_k over that shape's hits (differentiable w.r.t. ``params``'
    albedo, roughness and metallic)."""
    K = buf.K
    P = dr.width(pix)
    row = dr.arange(mi.UInt32, P * K)
    pos = dr.gather(mi.UInt32, pix, row // K) * K + row % K                  # [P*K]
    ids = dr.gather(mi.UInt32, buf.ids, pos)
    mine = (dr.gather(mi.UInt32, buf.slots, pos) == slot) & (ids != composite.INVALID)
    w = dr.select(mine, dr.gather(mi.Float, buf.w, pos), 0.0)
    inv = dr.rcp(dr.maximum(dr.block_sum(w, K), 1e-6))

    def blend(cls, src):
        v = dr.gather(cls, src, ids, mine, mode=expand_mode(src))
        return dr.block_sum(w * v, K) * inv
    return {"albedo": clamp_closed(blend(mi.Color3f, params.albedo), 0.0, 1.0),
            "roughness": clamp_closed(blend(mi.Float, params.roughness), 0.0, 1.0),
            "metallic": clamp_closed(blend(mi.Float, params.metallic), 0.0, 1.0)}
