"""The command line: ``comgs estimate-light``, ``compare-light``, ``train-completion``,
``train-light-head``, ``train-scene-label``.

``estimate-light`` takes its flags from its config dataclasses (``cli._flags``); the
trainers from theirs through the stage modules' ``add_arguments`` (also run as ``python -m
comgs_dr.stages.train_*``). The shared ``--out``/``--mitsuba-variant``/``--quiet`` come from
``core.config.shared_options``. The stages check the values; an error there exits 2 with its
message (``cli.main``).
"""
from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import numpy as np

from comgs_dr import set_variant
from comgs_dr.cli._flags import Spelling, add_config_flags, field_overrides
from comgs_dr.core import runlog
from comgs_dr.core.config import shared_options
from comgs_dr.eval.lighting_metrics import at_coarser, compare_maps
from comgs_dr.lighting import envmap
from comgs_dr.lighting.scene_label import LABEL_CHOICES
from comgs_dr.stages import train_completion, train_light_head, train_scene_label
from comgs_dr.stages.estimate_light import (
    BackendConfig,
    EstimateConfig,
    estimate_light,
    make_backend,
    output_paths,
    write_outputs,
)
from comgs_dr.stages.estimate_light_files import summary_text

# ----------------------------------------------------------------------------- estimate-light

ESTIMATE_FLAGS = {
    "label": Spelling(choices=LABEL_CHOICES, help="scene label (auto: classified from the "
                      "traced panorama)"),
    "width": Spelling(help="trace width"),
    "height": Spelling(help="trace height"),
    "exclude_radius": Spelling(help="leave out surfels this close to the position (the "
                               "object itself)"),
    "oct_res": Spelling(help="octahedral map side"),
    "net_resolution": Spelling(nargs=2, type=int, metavar=("H", "W"), help="network input "
                               "size (None: the size the weights were trained at)"),
    "sun_from_shadows": Spelling(choices=("auto", "off"), help="auto: a sun the panorama did "
                                 "not see is fitted to the scene's cast shadows "
                                 "(lighting.sun_fit); off: the panorama alone"),
    "sun_radius_deg": Spelling(help="angular radius of that sun, degrees (0, 10]"),
    "unseen_sky": Spelling(choices=("clear", "completion"), help="with that sun, the sky "
                           "the capture did not see: clear (a clear sky for the sun at the "
                           "completion's irradiance, lighting.clear_sky) or the completion's "
                           "guess"),
    "max_ground_albedo": Spelling(help="the unseen sky (with that sun, or with no sun where "
                                  "the capture barely saw the sky) is raised until the ground "
                                  "below reflects at most this of the light above (0: off)"),
    "sky_turbidity": Spelling(help="that clear sky's turbidity, [1, 10] (1.5 very clear ... "
                              "10 hazy); 0: the one whose sun/sky ratio is the shadows' k"),
}
BACKEND_FLAGS = {
    "backend": Spelling(choices=("net+sh", "net", "mean", "push_pull", "sh", "diffusers"),
                        help="completion backend (net+sh: the shipped weights, their hole "
                        "averaged with the SH fill, outdoors the weights' luminance in the "
                        "average's colour; net: the weights alone)"),
    "weights": Spelling(metavar="PATH", help="completion-net checkpoint (backends net+sh and "
                        "net; None: the shipped one)"),
    "diffusers_dir": Spelling(metavar="DIR", help="local diffusers inpainting model (backend "
                              "diffusers); prompt embeddings come from its text encoder or "
                              "DIR/ev_embeddings.pt ({'xi_b': [L, D], 'xi_d': [L, D]})"),
    "steps": Spelling(help="diffusion steps (backend diffusers)"),
}


def _add_estimate_light(sub) -> None:
    p = sub.add_parser(
        "estimate-light", parents=[shared_options(
            out=dict(required=True, metavar="ENV.exr", help="output equirect EXR"),
            quiet=False)],
        help="HDR environment map at a placement in a surfel scene",
        description="Trace a 360-degree panorama of the surfel scene at the "
                    "position, complete it at EV 0/-2.5/-5, fuse to HDR and write "
                    "ENV.exr (equirect), ENV_oct.exr (octahedral), ENV.json "
                    "(timings, lights, metadata) and ENV_preview.png.")
    # the inputs (not settings)
    p.add_argument("scene", metavar="SCENE.ply", help="surfel PLY (3DGS/2DGS/ComGS layouts)")
    p.add_argument("--at", nargs=3, type=float, required=True, metavar=("X", "Y", "Z"),
                   help="object placement (world coordinates, Z-up)")
    add_config_flags(p, EstimateConfig, ESTIMATE_FLAGS)
    add_config_flags(p, BackendConfig, BACKEND_FLAGS)
    p.set_defaults(func=_cmd_estimate_light)


def _cmd_estimate_light(args) -> int:
    set_variant(args.mitsuba_variant)
    cfg = EstimateConfig(**field_overrides(args, EstimateConfig))
    output_paths(args.out)                     # a bad --out fails now, not after the work
    backend = make_backend(BackendConfig(**field_overrides(args, BackendConfig)),
                           cfg.net_resolution)
    r = estimate_light(args.scene, args.at, cfg, backend)
    paths = write_outputs(r, args.out)
    print(summary_text(r, paths))
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
    # no settings: two inputs and where to write the scores (no config dataclass)
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


# ----------------------------------------------------------------------------- trainers

def _add_trainer(sub, name: str, module, help: str, description: str) -> None:
    """A ``comgs train-*`` subcommand: ``module.add_arguments`` (the fields of its config)
    beside the shared ``--out`` (``module.OUT_OPTION``) and ``--quiet``; runs
    ``module.run_from_args`` on the CPU variant."""
    p = sub.add_parser(name, parents=[shared_options(out=module.OUT_OPTION,
                                                     mitsuba_variant=False)],
                       help=help, description=description)
    module.add_arguments(p)
    p.set_defaults(func=partial(_run_trainer, module))


def _run_trainer(module, args) -> int:
    set_variant("llvm_ad_rgb")
    return module.run_from_args(args)


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
                 "leaving each real map out and on the held-out maps.")
