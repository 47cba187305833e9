"""Slow, obviously-right NumPy reference of surfel ray casting and compositing.

Every ray is tested against every surfel (no BVH, no hit buffer), hits are
sorted by distance and composited with the same rules as the fast path:
hit iff t > 0, |u| ≤ 3, |v| ≤ 3 (the ±3σ proxy quad) and α ≥ 1/255;
stop after K hits or once T < 1e-4.
"""
import numpy as np

C0, C1 = 0.28209479177387814, 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def frames(q):
    """[N,4] w-first -> t_u, t_v, n each [N,3]."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
    return R[:, :, 0], R[:, :, 1], R[:, :, 2]


def sh_eval(sh, d):
    """sh [K,3], d [3] -> colour [3] (3DGS convention)."""
    x, y, z = d
    b = [C0]
    K = sh.shape[0]
    if K > 1:
        b += [-C1 * y, C1 * z, -C1 * x]
    if K > 4:
        b += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * z * z - x * x - y * y), C2[3] * x * z,
              C2[4] * (x * x - y * y)]
    if K > 9:
        b += [C3[0] * y * (3 * x * x - y * y), C3[1] * x * y * z, C3[2] * y * (4 * z * z - x * x - y * y),
              C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y), C3[4] * x * (4 * z * z - x * x - y * y),
              C3[5] * z * (x * x - y * y), C3[6] * x * (x * x - 3 * y * y)]
    return np.maximum(np.asarray(b) @ sh + 0.5, 0.0)


def render_rays(p: dict, o, d, K=32, alpha_min=1 / 255, alpha_max=0.99, t_min=1e-4):
    """p: SurfelParams.to_numpy(); o, d: [R,3]. Returns dict of buffers and hit lists."""
    p = {k: np.asarray(v, np.float64) for k, v in p.items()}
    tu, tv, n = frames(p["quats"])
    s = np.exp(np.clip(p["log_scales"], -20, 12))
    op = 1 / (1 + np.exp(-np.clip(p["opacity_logit"], -30, 30)))
    R = o.shape[0]
    out = {k: np.zeros((R, c)) for k, c in [("color", 3), ("weight", 1), ("depth", 1), ("normal", 3),
                                           ("albedo", 3), ("roughness", 1), ("metallic", 1)]}
    hits = []
    for r in range(R):
        dn = n @ d[r]                                      # [N]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ij,ij->i", p["means"] - o[r], n) / dn
        x = o[r] + t[:, None] * d[r] - p["means"]
        u = np.einsum("ij,ij->i", x, tu) / s[:, 0]
        v = np.einsum("ij,ij->i", x, tv) / s[:, 1]
        alpha = np.minimum(op * np.exp(-0.5 * (u * u + v * v)), alpha_max)
        ok = (np.abs(dn) > 1e-12) & (t > 0) & (np.abs(u) <= 3) & (np.abs(v) <= 3) & (alpha >= alpha_min) \
            & (op >= alpha_min)
        idx = np.nonzero(ok)[0]
        idx = idx[np.argsort(t[idx], kind="stable")]
        T, used = 1.0, []
        for i in idx:
            if len(used) == K or T < t_min:
                break
            w = T * alpha[i]
            nrm = -n[i] if n[i] @ d[r] > 0 else n[i]
            out["color"][r] += w * sh_eval(p["sh"][i], d[r])
            out["weight"][r] += w
            out["depth"][r] += w * t[i]
            out["normal"][r] += w * nrm
            out["albedo"][r] += w * p["albedo"][i]
            out["roughness"][r] += w * p["roughness"][i]
            out["metallic"][r] += w * p["metallic"][i]
            T *= 1 - alpha[i]
            used.append(int(i))
        hits.append(used)
    out["hits"] = hits
    return out
