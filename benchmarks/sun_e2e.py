"""End to end: does ``estimate_light`` give a clipped sun its power back?

For each real outdoor map (default: the held-out ones with a sun, ``pano_data.HELD_OUT``),
a surfel scene is built as a perfect step-1 reconstruction of an LDR capture would hold it:

* a textured ground disc (radius 15) whose display colour is albedo·E_up/π of the map
  (unshadowed), and
* the part of the sky the capture saw: a dome (radius 40) of surfels, one per pixel of the map
  area-resampled to ``--dome-res`` × 2·res, over ±``--wedge``/2 of azimuth around the sun and
  up to ``--max-elev`` degrees, each holding the pixel's EV-0 display colour (clipped at 1:
  the capture is LDR, exposed by ``pano_data.auto_exposure``).

``estimate_light`` then traces that scene from 1 m above the ground and completes it with each
method. The truth is the map itself above the horizon and the ground's radiance below. The
score is the issue's: E(facing the true dominant light) / E(facing up) of the estimate
against that of the truth (``eval.lighting_metrics.compare_maps``), plus the dominant light's
angular error and the total power ratio.

    python benchmarks/sun_e2e.py [--maps a.exr b.hdr] [--res 128] [--dome-res 128]

The shipped light head was fitted on every shared map; with ``--light-head default`` a map
whose fold of it is kept (the held-out maps, ``cv_heads.held_out_head``) is estimated with
that fold, the head fitted the same way without the map (a comment line says so).
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np


def _frame_quats(normals):
    from comgs_dr.surfels.from_mesh import frame_to_quat
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    a = np.where(np.abs(n[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    tu = np.cross(a, n)
    tu /= np.linalg.norm(tu, axis=1, keepdims=True)
    return frame_to_quat(np.stack([tu, np.cross(n, tu), n], 2))


def build_scene(env, sun_dir, dome_res: int, wedge_deg: float, max_elev_deg: float,
                seed: int = 0):
    """(Mitsuba scene, true map at [dome_res, 2·dome_res]) for an exposed map ``env``."""
    import mitsuba as mi

    from comgs_dr.core.colorspace import LUMA
    from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles
    from comgs_dr.eval.lighting_metrics import irradiance
    from comgs_dr.lighting.hdr import area_resize_equirect, expose
    from comgs_dr.surfels.params import SurfelParams, sh_from_base_colour
    from comgs_dr.surfels.shape import SurfelShapeBase
    h, w = dome_res, 2 * dome_res
    sky = area_resize_equirect(env, h, w)                                     # [h, w, 3]
    d = equirect_directions(h, w)
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    az = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    saz = np.degrees(np.arctan2(sun_dir[1], sun_dir[0]))
    daz = np.abs((az - saz + 180.0) % 360.0 - 180.0)
    elev = np.degrees(np.arcsin(np.clip(d[..., 2], -1, 1)))
    seen = (d[..., 2] > 0) & (daz <= wedge_deg / 2) & (elev <= max_elev_deg)
    R, G, pos = 40.0, 15.0, np.array([0.0, 0.0, 1.0])
    dirs = d[seen]                                                            # [M, 3]
    theta = np.arccos(np.clip(dirs[:, 2], -1, 1))
    ext_v = R * np.pi / h
    ext_u = R * (2 * np.pi / w) * np.sin(theta)
    means = [pos + R * dirs]
    normals = [-dirs]
    scales = [np.stack([0.6 * np.maximum(ext_u, 1e-3), np.full(len(dirs), 0.6 * ext_v)], 1)]
    cols = [sky[seen]]
    # ground: a jittered grid, albedo from value noise, lit by the upper hemisphere
    rng = np.random.default_rng(seed)
    step = 0.2
    g = np.arange(-G, G + 1e-9, step)
    gx, gy = np.meshgrid(g, g)
    keep = gx ** 2 + gy ** 2 <= G * G
    gx, gy = gx[keep] + rng.uniform(-0.05, 0.05, keep.sum()), gy[keep]
    upper = np.where(d[..., 2:] > 0, sky, 0.0)
    e_up = irradiance(upper, np.array([0.0, 0.0, 1.0]))
    tint = np.array([0.55, 0.45, 0.35])
    albedo = tint * (0.6 + 0.5 * np.sin(0.7 * gx)[:, None] * np.cos(0.9 * gy)[:, None] ** 2)
    rgb_e = (upper * dw[..., None]).sum((0, 1))
    e_col = e_up * rgb_e / max(float(rgb_e @ LUMA), 1e-12)                  # coloured E_up
    means.append(np.stack([gx, gy, np.zeros_like(gx)], 1))
    normals.append(np.tile([0.0, 0.0, 1.0], (len(gx), 1)))
    scales.append(np.full((len(gx), 2), 0.6 * step))
    cols.append(albedo * e_col / np.pi)
    means, normals, scales, cols = (np.concatenate(x) for x in (means, normals, scales, cols))
    sh = sh_from_base_colour(expose(cols, 0.0))                      # the LDR capture
    params = SurfelParams.from_numpy(means, _frame_quats(normals), np.log(scales),
                                     np.full(len(means), 6.0), sh)
    scene = mi.load_dict({"type": "scene",
                          "scene": SurfelShapeBase.from_params(params, id="scene")})
    ground = (albedo.mean(0) * e_col / np.pi)
    truth = np.where(d[..., 2:] > 0, sky, ground)
    return scene, truth


def outdoor_maps(paths) -> list[Path]:
    """``paths`` as Paths, or (None/empty) the held-out outdoor shared maps."""
    if paths:
        return [Path(m) for m in paths]
    from comgs_dr.data.synthetic import shared_data_dir
    from comgs_dr.lighting import pano_data
    return [p for p in sorted((shared_data_dir() / "hdri").glob("*"))
            if p.stem in pano_data.HELD_OUT and pano_data.label_of(p.stem) == "outdoor"]


def e2e_methods(head: str = "default", weights=None) -> tuple[dict, dict]:
    """({method: (backend key, light head)}, {backend key: backend}): ``default`` is
    estimate-light's (``backends.default_backend`` + the head); the net and push_pull with and
    without the head. ``weights``: a completion checkpoint (None: the shipped one)."""
    from comgs_dr.lighting import backends
    net = backends.load_network_backend(weights)
    be = {"net": net, "push_pull": backends.FillBackend("push_pull"),
          "default": backends.net_sh_blend(net)}
    methods = {"default": ("default", head), "net+lights": ("net", head), "net": ("net", "none"),
               "push_pull": ("push_pull", "none"), "push_pull+lights": ("push_pull", head)}
    return methods, be


def map_head(stem: str, head) -> str:
    """``head`` for map ``stem``, but the shipped head's cross-validation fold for a map it
    was fitted on and whose fold is kept (``cv_heads.held_out_head``), said in a comment
    line: the score stays a held-out one."""
    from cv_heads import held_out_head
    h = held_out_head(stem, head)
    if str(h) != str(head):
        print(f"<!-- {stem}: light head {Path(h).relative_to(Path(h).parents[2])} "
              f"(the shipped head's fold without this map) -->", flush=True)
    return str(h)


TABLE_HEAD = ("| map | method | coverage | light angle ° | E_sun/E_up est | E_sun/E_up true | "
              "ratio error | power est/true | s |\n|---|---|---|---|---|---|---|---|---|")


def score(stem: str, name: str, r: dict, truth, seconds: float) -> dict:
    """Score an ``estimate_light`` result against the true map, print its table row and
    return {map, method, ratio_err, angle, power}."""
    from comgs_dr.eval.lighting_metrics import compare_maps
    m = compare_maps(r["hdr"], truth)
    est_r, gt_r = m["light_up_irradiance_ratio_est"], m["light_up_irradiance_ratio_gt"]
    err = est_r / gt_r - 1.0
    print(f"| {stem} | {name} | {100 * r['coverage']:.0f} % | "
          f"{m.get('light_angle_deg', float('nan')):.1f} | {est_r:.2f} | {gt_r:.2f} | "
          f"{100 * err:+.0f} % | {m['power_ratio_est_gt']:.2f} | {seconds:.1f} |", flush=True)
    return {"map": stem, "method": name, "ratio_err": err, "angle": m.get("light_angle_deg"),
            "power": m["power_ratio_est_gt"]}


def print_summary(rows: list, methods) -> None:
    for name in methods:
        e = [abs(r["ratio_err"]) for r in rows if r["method"] == name]
        print(f"{name}: mean |ratio error| {100 * np.mean(e):.0f} %, within 25 %: "
              f"{sum(x <= 0.25 for x in e)}/{len(e)}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--maps", nargs="*", default=None, help="equirect maps (default: the "
                    "held-out outdoor shared maps)")
    ap.add_argument("--res", type=int, default=128, help="trace height (width 2x)")
    ap.add_argument("--dome-res", type=int, default=128)
    ap.add_argument("--wedge", type=float, default=180.0, help="azimuth range seen, degrees")
    ap.add_argument("--max-elev", type=float, default=60.0)
    ap.add_argument("--light-head", default="default")
    ap.add_argument("--weights", default=None, help="completion checkpoint (default: shipped)")
    ap.add_argument("--trust-brackets", type=float, default=None, help="EstimateConfig."
                    "light_trust_brackets (default: its default)")
    ap.add_argument("--label", choices=("outdoor", "auto", "indoor", "unknown"),
                    default="outdoor", help="estimate-light's scene label (auto: classified "
                    "from the trace, lighting.scene_label)")
    ap.add_argument("--skies", type=int, default=0, help="also this many Mitsuba sunsky "
                    "skies (seeds never used in training; sun above 8°)")
    a = ap.parse_args(argv)
    import comgs_dr
    comgs_dr.set_variant("llvm_ad_rgb")
    from comgs_dr.lighting import pano_data
    from comgs_dr.lighting.hdr import extract_lights
    from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light
    maps = outdoor_maps(a.maps)
    cases = [(p.stem, pano_data.load_map(p, 256, 512).astype(np.float64)) for p in maps]
    rng = np.random.default_rng(12345)
    while len(cases) < len(maps) + a.skies:
        sky = pano_data.sunsky_panorama(rng, 256, 512).astype(np.float64)
        sun = extract_lights(sky, k=1)
        if sun and sun[0]["direction"][2] > np.sin(np.radians(8)):
            cases.append((f"sunsky_{len(cases) - len(maps)}", sky))
    methods, be = e2e_methods(a.light_head, a.weights)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; trace {2 * a.res}x{a.res}, "
          f"dome {2 * a.dome_res}x{a.dome_res}, sky seen: ±{a.wedge / 2:g}° around the sun up "
          f"to {a.max_elev:g}°\n")
    print(TABLE_HEAD)
    rows = []
    for stem, env in cases:
        env = env * pano_data.auto_exposure(env)
        sun = extract_lights(env, k=1)[0]["direction"]
        scene, truth = build_scene(env, sun, a.dome_res, a.wedge, a.max_elev)
        heads = {"default": map_head(stem, "default")} if a.light_head == "default" else {}
        for name, (kind, head) in methods.items():
            t0 = time.perf_counter()
            kw = {} if a.trust_brackets is None else {"light_trust_brackets": a.trust_brackets}
            cfg = EstimateConfig(width=2 * a.res, height=a.res, oct_res=32, label=a.label,
                                 light_head=heads.get(head, head), **kw)
            r = estimate_light(scene, [0.0, 0.0, 1.0], cfg, be[kind])
            dt = time.perf_counter() - t0
            rows.append(score(stem, name, r, truth, dt))
            if name == "default" and r["meta"].get("p_outdoor") is not None:
                print(f"<!-- {stem}: label auto -> {r['meta']['label']} "
                      f"(p(outdoor) {r['meta']['p_outdoor']:.2f}) -->", flush=True)
    print()
    print_summary(rows, methods)
    return rows


if __name__ == "__main__":
    main()
