"""Trace-initialisation of probe textures (paper: SOP textures "initialized via ray tracing").

For probe k and texel t, rays leave the probe position p_k in the texel's direction(s);
the surfel composite along each ray gives occlusion O = 1 − T and indirect radiance L_in
(``surfels.trace``). With ``supersample = s`` each texel averages s×s stratified
directions inside it (s = 1: the texel centre).
"""
from __future__ import annotations

import numpy as np
from tqdm.auto import tqdm

from comgs_dr.core import octahedral as octa
from comgs_dr.sops.probes import ProbeSet
from comgs_dr.surfels.trace import trace_visibility_np


def texel_directions(res: int, supersample: int = 1, seed: int = 0) -> np.ndarray:
    """Unit directions [R*R*s*s, 3], texel-major (all s² rays of texel 0 first).
    s = 1: texel centres; s > 1: one jittered direction per stratum of each texel."""
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be ≥ 1, got {supersample}")
    if s == 1:
        return octa.texel_directions_np(res)
    rng = np.random.default_rng(seed)
    ty, tx, sy, sx = np.meshgrid(np.arange(res), np.arange(res), np.arange(s), np.arange(s),
                                 indexing="ij")
    j = rng.uniform(0, 1, (2,) + tx.shape)
    u = (tx + (sx + j[0]) / s) / res
    v = (ty + (sy + j[1]) / s) / res
    return octa.uv_to_dir_np(np.stack([u.ravel(), v.ravel()], -1))


def bake(scene, probes: ProbeSet, max_hits: int = 8, supersample: int = 1,
         colour_space: str = "srgb", radiance: bool = True, chunk: int = 1 << 19,
         progress: bool = True) -> ProbeSet:
    """Fill ``probes.texture`` by tracing ``scene`` (surfels only) from every probe.

    ``radiance=False`` bakes occlusion only (RGB left at 0), e.g. for shadow probes.
    Returns the same ProbeSet (texture replaced). Rays per probe: R²·s².
    """
    dirs = texel_directions(probes.res, supersample)                   # [R²s², 3]
    per = len(dirs)
    n = probes.count * per
    bar = tqdm(total=n, desc="bake SOPs", unit="ray", unit_scale=True, disable=not progress)
    occ = np.empty(n, np.float32)
    rad = np.zeros((n, 3), np.float32)
    step = max(1, chunk // per)                                        # probes per chunk
    for s in range(0, probes.count, step):
        e = min(probes.count, s + step)
        o = np.repeat(probes.positions[s:e], per, axis=0)
        d = np.tile(dirs, (e - s, 1))
        O, L = trace_visibility_np(scene, o, d, chunk=chunk, max_hits=max_hits,
                                   radiance=radiance, colour_space=colour_space)
        occ[s * per:e * per] = O
        if L is not None:
            rad[s * per:e * per] = L
        bar.update(len(o))
    bar.close()
    ss = supersample * supersample
    r = probes.res
    tex = np.concatenate([rad, occ[:, None]], -1).reshape(probes.count, r * r, ss, 4).mean(2)
    probes.texture = np.ascontiguousarray(tex.reshape(probes.count, r, r, 4), np.float32)
    probes.meta.update(baked={"max_hits": max_hits, "supersample": supersample,
                              "radiance": radiance, "colour_space_of_field": colour_space})
    return probes
