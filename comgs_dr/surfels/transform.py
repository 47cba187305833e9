"""Placing surfels in a scene: a similarity transform of every surfel (centre, rotation,
scales) and of its view-dependent SH colour.

Centres: p' = s·R·p + t; rotations: q' = q_R ⊗ q (w-first Hamilton product; the stored
quaternion stays unnormalised with its norm kept); scales: log σ' = log σ + log s. SH bands
rotate among themselves: colour'(d) = colour(Rᵀd), so each band's coefficients are mapped by
the (2l+1)² matrix M_l with Y_l(Rᵀd) = M_lᵀ·Y_l(d), fitted exactly by least squares over
directions (a band is closed under rotation, so the fit is exact up to rounding; written here
because no library in the stack rotates real SH in the 3DGS basis).
"""
from __future__ import annotations

import mitsuba as mi
import numpy as np

from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.similarity import Similarity
from comgs_dr.surfels import kernel as K
from comgs_dr.surfels.params import SurfelParams


def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a proper rotation matrix [3, 3] (Shepperd's method)."""
    r = np.asarray(r, np.float64)
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = np.empty(4)
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.asarray(q, np.float64)
    return q / np.linalg.norm(q)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions, broadcasting over leading axes."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], -1)


def _sh_basis_np(d: np.ndarray, degree: int) -> np.ndarray:
    """[N, (deg+1)²] real SH basis of the 3DGS convention (``kernel.sh_basis``)."""
    v = to_jit(mi.Vector3f, d.T)
    return np.stack([np.asarray(b, np.float64) for b in K.sh_basis(v, degree)], 1)


def sh_rotation(rotation: np.ndarray, degree: int) -> np.ndarray:
    """[(deg+1)², (deg+1)²] block-diagonal M with colour'(d) = colour(Rᵀd) for c' = M·c."""
    k = (degree + 1) ** 2
    m = np.zeros((k, k))
    m[0, 0] = 1.0
    if degree == 0:
        return m
    rng = np.random.default_rng(0)
    d = rng.normal(size=(256, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    y = _sh_basis_np(d, degree)                          # [S, k]  Y(d)
    yr = _sh_basis_np(d @ np.asarray(rotation), degree)  # [S, k]  Y(Rᵀd): rows of d·R = (Rᵀd)ᵀ
    for l in range(1, degree + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        # want Y_l(d)·c' = Y_l(Rᵀd)·c for all c  ->  M_l = pinv(Y_l(d)) Y_l(Rᵀd)
        m[sl, sl] = np.linalg.lstsq(y[:, sl], yr[:, sl], rcond=None)[0]
    return m


def transform_surfels(params: SurfelParams, sim: Similarity) -> SurfelParams:
    """A copy of ``params`` placed by ``sim`` (object → world)."""
    d = params.to_numpy()
    d["means"] = sim.points(d["means"]).astype(np.float32)
    qr = quat_from_matrix(sim.rotation)
    d["quats"] = quat_mul(qr[None], d["quats"]).astype(np.float32)
    d["log_scales"] = (d["log_scales"] + np.log(sim.scale)).astype(np.float32)
    sh = np.asarray(d["sh"], np.float64)                 # [N, K, 3]
    deg = params.sh_degree
    if deg > 0:
        m = sh_rotation(sim.rotation, deg)
        d["sh"] = np.einsum("ij,njc->nic", m, sh).astype(np.float32)
    return SurfelParams.from_numpy(**d)
