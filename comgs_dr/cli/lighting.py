"""The command line: ``comgs estimate-light``, ``compare-light``, ``train-completion``,
``train-light-head``, ``train-scene-label``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from comgs_dr import set_variant
from comgs_dr.core import runlog
from comgs_dr.core.config import add_config_arguments, config_overrides
from comgs_dr.eval.lighting_metrics import at_coarser, compare_maps
from comgs_dr.lighting import backends, envmap, lights
from comgs_dr.stages import train_completion, train_light_head, train_scene_label
from comgs_dr.stages.estimate_light import (
    EstimateConfig,
    estimate_light,
    output_paths,
    write_outputs,
)
from comgs_dr.stages.estimate_light_files import sky_text

# ----------------------------------------------------------------------------- estimate-light

def _add_estimate_light(sub) -> None:
    d = EstimateConfig()
    p = sub.add_parser("estimate-light", help="HDR environment map at a placement in a surfel scene",
                       description="Trace a 360-degree panorama of the surfel scene at the "
                                   "position, complete it at EV 0/-2.5/-5, fuse to HDR and write "
                                   "ENV.exr (equirect), ENV_oct.exr (octahedral), ENV.json "
                                   "(timings, lights, metadata) and ENV_preview.png.")
    p.add_argument("scene", metavar="SCENE.ply", help="surfel PLY (3DGS/2DGS/ComGS layouts)")
    p.add_argument("--at", nargs=3, type=float, required=True, metavar=("X", "Y", "Z"),
                   help="object placement (world coordinates, Z-up)")
    p.add_argument("--out", required=True, metavar="ENV.exr", help="output equirect EXR")
    p.add_argument("--label", choices=("auto", "unknown", "indoor", "outdoor"), default=d.label,
                   help="scene label (default auto: classified from the traced panorama)")
    p.add_argument("--width", type=int, default=d.width, help=f"trace width (default {d.width})")
    p.add_argument("--height", type=int, default=d.height,
                   help=f"trace height (default {d.height})")
    p.add_argument("--exclude-radius", type=float, default=d.exclude_radius,
                   help="leave out surfels this close to the position (the object itself)")
    p.add_argument("--max-hits", type=int, default=d.max_hits)
    p.add_argument("--supersample", type=int, default=d.supersample)
    p.add_argument("--oct-res", type=int, default=d.oct_res,
                   help=f"octahedral map side (default {d.oct_res})")
    p.add_argument("--backend", choices=("net+sh", "net", "mean", "push_pull", "sh", "diffusers"),
                   default="net+sh", help="completion backend (default net+sh: the shipped "
                   "weights, their hole averaged with the SH fill, outdoors the weights' "
                   "luminance in the average's colour; net: the weights alone)")
    p.add_argument("--weights", metavar="PATH", help="completion-net checkpoint (backends "
                   "net+sh and net; default: the shipped one)")
    p.add_argument("--net-resolution", type=int, nargs=2, metavar=("H", "W"),
                   help="network input size (default: the size the weights were trained at)")
    p.add_argument("--diffusers-dir", metavar="DIR",
                   help="local diffusers inpainting model (backend diffusers); prompt "
                        "embeddings come from its text encoder or DIR/ev_embeddings.pt "
                        "({'xi_b': [L, D], 'xi_d': [L, D]})")
    p.add_argument("--steps", type=int, default=30, help="diffusion steps (backend diffusers)")
    p.add_argument("--variant", default="auto", metavar="MITSUBA_VARIANT",
                   help="Mitsuba variant: auto (default), llvm_ad_rgb (CPU) or cuda_ad_rgb")
    add_config_arguments(p, EstimateConfig)
    p.set_defaults(func=_cmd_estimate_light)


def _check_backend_flags(args) -> None:
    """ValueError for a flag the chosen backend would ignore."""
    net = args.backend in ("net", "net+sh")
    for flag, value, applies in (("--weights", args.weights, net),
                                 ("--net-resolution", args.net_resolution, net),
                                 ("--diffusers-dir", args.diffusers_dir,
                                  args.backend == "diffusers")):
        if value is not None and not applies:
            raise ValueError(f"{flag} does not apply to --backend {args.backend}")


def _estimate_backend(args):
    _check_backend_flags(args)
    if args.backend in ("net", "net+sh"):
        res = tuple(args.net_resolution) if args.net_resolution else None
        net = backends.load_network_backend(args.weights, res)
        return net if args.backend == "net" else backends.net_sh_blend(net)
    if args.backend == "diffusers":
        if not args.diffusers_dir:
            raise ValueError("--backend diffusers needs --diffusers-dir DIR")
        return backends.DiffusersBackend.from_dir(args.diffusers_dir, steps=args.steps)
    return backends.FillBackend(args.backend)


def _cmd_estimate_light(args) -> int:
    set_variant(args.variant)
    kw = config_overrides(args, EstimateConfig)
    if "net_resolution" in kw:
        kw["net_resolution"] = tuple(kw["net_resolution"])
    cfg = EstimateConfig(**kw)
    output_paths(args.out)                     # a bad --out fails now, not after the work
    r = estimate_light(args.scene, args.at, cfg, _estimate_backend(args))
    paths = write_outputs(r, args.out)
    hot = sum(bool(l.get("above_white")) for l in r["lights"])
    print(f"coverage {100 * r['coverage']:.1f}%, backend {r['meta']['backend']}, "
          f"{len(r['lights'])} brightest region(s), {hot} of them above the EV-0 white level "
          f"(lights), peak radiance {float(r['hdr'].max()):.3g}")
    print(sky_text(r["meta"]))
    if r["meta"].get("p_outdoor") is not None:
        print(f"label auto -> {r['meta']['label']} (p(outdoor) {r['meta']['p_outdoor']:.2f})")
    for i, g in enumerate(r.get("light_regions", [])):     # what the light head did
        el = float(np.degrees(np.arcsin(np.clip(g["direction"][2], -1.0, 1.0))))
        print(f"clipped region {i}: {g['solid_angle']:.4g} sr at elevation {el:+.1f}°, "
              f"gain {g['gain']:.3g}, power {g['predicted_power']:.3g} (after the brackets' "
              f"vote {g['voted_power']:.3g}), map {g['brackets_power']:.3g} -> {g['power']:.3g} "
              f"({g['action']})")
    dom = r["meta"].get("light_dominance")
    if dom is not None:
        print(f"strongest observed clipped light: {dom:.2f}x the next"
              + (" (a near tie: see light_head_regions in the JSON)"
                 if dom < lights.DOMINANCE_MARGIN else ""))
    print(f"{'step':<12}{'seconds':>10}")
    for k, v in r["timings"].items():
        print(f"{k:<12}{v:>10.3f}")
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


# ----------------------------------------------------------------------------- compare-light

def _add_compare_light(sub) -> None:
    p = sub.add_parser("compare-light", help="score an estimated environment map against the "
                       "true light (e.g. a dataset's probes/<object>.exr)",
                       description="Array-of-spheres si-RMSE and colour angular error (diffuse, "
                                   "matte silver), the angle between the dominant lights, the "
                                   "irradiance ratio E(facing the true dominant light) / E(up) "
                                   "of each map and the total power ratio "
                                   "(comgs_dr.eval.lighting_metrics.compare_maps). Both maps are "
                                   "linear equirect or octahedral files of any size; the finer "
                                   "is area-averaged to the coarser.")
    p.add_argument("estimate", metavar="EST.exr")
    p.add_argument("truth", metavar="TRUE.exr")
    p.add_argument("--json", metavar="PATH", help="also write the scores here")
    p.add_argument("--png", metavar="PATH", help="also write the two maps side by side (the "
                   "truth's exposure, tone-mapped)")
    p.set_defaults(func=_cmd_compare_light)


def _equirect(path) -> np.ndarray:
    img, layout = envmap.read_envmap_file(path)
    return envmap.oct_to_equirect_np(img, 2 * img.shape[0]) if layout == "octahedral" else img


def _el_az(d) -> str:
    """"elevation / azimuth" in degrees of a Z-up direction (azimuth atan2(y, x))."""
    x, y, z = (float(v) for v in d)
    return f"{np.degrees(np.arcsin(np.clip(z, -1.0, 1.0))):.1f} / {np.degrees(np.arctan2(y, x)):.1f}"


def _cmd_compare_light(args) -> int:
    est, gt = at_coarser(_equirect(args.estimate), _equirect(args.truth))   # compared, shown
    m = compare_maps(est, gt)
    rows = [(f"spheres {k}: si-RMSE / angular error °",
             f"{v['si_rmse']:.4f} / {v['angular_deg']:.2f}") for k, v in m["spheres"].items()]
    re, rg = m.get("light_up_irradiance_ratio_est"), m.get("light_up_irradiance_ratio_gt")
    if m.get("light_angle_deg") is not None:
        rows.append(("dominant light angle °", f"{m['light_angle_deg']:.2f}"))
    for key, name in (("est_light_direction", "estimate"), ("true_light_direction", "truth")):
        if m.get(key) is not None:
            rows.append((f"dominant light of the {name}: elevation / azimuth °",
                         _el_az(m[key])))
    if re is not None and rg is not None:
        rows.append(("E(light)/E(up): estimate / truth / error",
                     f"{re:.3f} / {rg:.3f} / {100 * (re / rg - 1):+.1f} %"))
    rows.append(("power estimate / truth", f"{m['power_ratio_est_gt']:.3f}"))
    w = max(len(r[0]) for r in rows)
    print("\n".join(f"{a:<{w}}  {b}" for a, b in rows))
    if args.json:
        Path(args.json).write_text(json.dumps(runlog.json_safe(m), indent=1, allow_nan=False))
    if args.png:
        from comgs_dr.demo import envmap_figure
        envmap_figure(gt, est).save(args.png)
    return 0


# ----------------------------------------------------------------------------- train-completion

def _add_trainer(sub, name: str, module, help: str, description: str) -> None:
    """A ``comgs train-*`` subcommand: ``module.add_arguments`` / ``module.run_from_args``,
    on the CPU variant."""
    p = sub.add_parser(name, help=help, description=description)
    module.add_arguments(p)

    def run(args) -> int:
        set_variant("llvm_ad_rgb")
        return module.run_from_args(args)
    p.set_defaults(func=run)


def _add_train_completion(sub) -> None:
    _add_trainer(sub, "train-completion", train_completion,
                 "train the panorama completion network",
                 "Generate the training set (Poly Haven maps minus the held-out ones, sunsky "
                 "skies, path-traced rooms, traced surfel masks) and train the EV-conditioned "
                 "completion network in two steps within --minutes.")


def _add_train_light_head(sub) -> None:
    _add_trainer(sub, "train-light-head", train_light_head,
                 "train the light head (power of clipped lights)",
                 "Generate clipped-light regions from the real maps minus the held-out ones, "
                 "sunsky skies and path-traced rooms at several sizes, and fit the light head "
                 "(minutes).")


def _add_train_scene_label(sub) -> None:
    _add_trainer(sub, "train-scene-label", train_scene_label,
                 "train the indoor/outdoor classifier (estimate-light --label auto)",
                 "Draw masked, re-exposed panoramas from the real maps minus the held-out ones, "
                 "sunsky skies and path-traced rooms, fit the logistic classifier, and score it "
                 "leaving each real map out and on the held-out maps (about 3 minutes).")
