"""The command line: ``comgs compose``, ``render-comp``."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from comgs_dr import set_variant
from comgs_dr.lighting import backends
from comgs_dr.stages.compose import PRESETS as COMPOSE_PRESETS
from comgs_dr.stages.compose import compose
from comgs_dr.stages.estimate_light import (
    EstimateConfig,
    check_model_files,
    estimate_light,
    write_outputs,
)
from comgs_dr.stages.render_comp import VARIANTS as RENDER_VARIANTS
from comgs_dr.stages.render_comp import render_comp
from comgs_dr.surfels.edit import parse_material_spec

# ----------------------------------------------------------------------------- compose

def _add_compose(sub) -> None:
    p = sub.add_parser(
        "compose", help="edit stage: place objects in a scene, light them, cache occlusion",
        description="Place step-2 objects in a step-1 scene (transform.json: row-major 4x4 "
                    "object-to-world 'transform', or location/rotation (Euler XYZ degrees)/"
                    "scale; similarity transforms only), light each object (--env: one map, "
                    "an equirect .hdr/.exr in the package's Z-up convention, u = 0.5 - "
                    "atan2(y, x)/2pi, v = acos(z)/pi, or our octahedral EXR; without --env "
                    "the lighting is estimated at each object's centre as `comgs "
                    "estimate-light` does), place shadow-region probes on the scene around "
                    "every object and trace their occlusion against all objects. Writes "
                    "COMP_DIR/composition.json, composition.xml, edit.json (timings); moving "
                    "one object later re-traces only what it touches (COMP_DIR/cache).")
    p.add_argument("scene_run", metavar="SCENE_RUN", help="`comgs reconstruct` folder of the scene")
    p.add_argument("--object", action="append", required=True, metavar="NAME=OBJECT_RUN",
                   help="an object: its name in transform.json and its `comgs decompose` "
                        "folder (or the reconstruct folder holding material/); repeatable")
    p.add_argument("--placement", required=True, metavar="transform.json")
    p.add_argument("--env", metavar="MAP", help="map lighting every object (default: estimate)")
    p.add_argument("--out", required=True, metavar="COMP_DIR")
    p.add_argument("--preset", choices=sorted(COMPOSE_PRESETS), default="default",
                   help="default: 10k shadow probes per object (paper), 32² texels; fast: "
                        "2k at 16² (20x fewer occlusion rays; shadows softer and "
                        "weaker, most under a low sun)")
    p.add_argument("--shadow-probes", type=int, metavar="N", help="shadow probes per object")
    p.add_argument("--sun-from-shadows", choices=("auto", "off"), default=None,
                   dest="sun_from_shadows",
                   help="auto (default): a sun the scene capture did not see is fitted to the "
                        "scene's cast shadows (lighting.sun_fit); off: the panorama alone; "
                        "not with --env")
    p.add_argument("--label", choices=("auto", "unknown", "indoor", "outdoor"), default=None,
                   help="scene label for the lighting estimation (default auto: classified "
                   "from the traced panorama; not with --env)")
    p.add_argument("--weights", metavar="W.pt", default=None,
                   help="completion-net checkpoint of the estimation (default: the shipped one; "
                   "not with --env)")
    p.add_argument("--light-head", metavar="HEAD.pt", default=None,
                   help="light head of the estimation: a file, or none (default: the shipped "
                   "one; not with --env)")
    p.add_argument("--scene-label", metavar="M.json", default=None,
                   help="the classifier of label auto (default: the shipped one; e.g. from "
                   "`comgs train-scene-label`; not with --env)")
    p.add_argument("--variant", default="auto", metavar="MITSUBA_VARIANT",
                   help="Mitsuba variant: auto (default), llvm_ad_rgb (CPU) or cuda_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_compose)


def _cmd_compose(args) -> int:
    set_variant(args.variant)
    objects = {}
    for spec in args.object:
        name, sep, run = spec.partition("=")
        if not sep or not name or not run:
            raise ValueError(f"--object expects NAME=OBJECT_RUN, got {spec!r}")
        if name in objects:
            raise ValueError(f"--object {name!r} given twice")
        objects[name] = run
    cfg = COMPOSE_PRESETS[args.preset]
    if args.shadow_probes is not None:
        if args.shadow_probes < 1:
            raise ValueError(f"--shadow-probes must be ≥ 1, got {args.shadow_probes}")
        cfg = dataclasses.replace(cfg, shadow=dataclasses.replace(cfg.shadow,
                                                                  count=args.shadow_probes))
    estimator = None
    if args.env is not None:
        for flag, value in (("--label", args.label), ("--scene-label", args.scene_label),
                            ("--weights", args.weights), ("--light-head", args.light_head),
                            ("--sun-from-shadows", args.sun_from_shadows)):
            if value is not None:
                raise ValueError(f"{flag} sets up the lighting estimation; with --env the map "
                                 f"is the light and nothing is estimated")
    else:
        scene_ply = str(Path(args.scene_run) / "point_cloud.ply")
        ecfg = EstimateConfig(label=args.label or "auto",
                              scene_label=args.scene_label or "default",
                              light_head=args.light_head or "default",
                              sun_from_shadows=args.sun_from_shadows or "auto")
        ecfg.validate()
        check_model_files(ecfg)
        if args.weights is not None and not Path(args.weights).is_file():
            raise FileNotFoundError(f"--weights: completion weights not found: {args.weights} "
                                    f"(or estimate the map with `comgs estimate-light "
                                    f"--backend push_pull` and give it as --env)")
        backend = (backends.default_backend() if args.weights is None else
                   backends.net_sh_blend(backends.load_network_backend(args.weights)))

        def estimator(pos, name):
            r = estimate_light(scene_ply, pos, ecfg, backend)
            at = np.round(np.asarray(pos, float), 3).tolist()
            if r["meta"].get("p_outdoor") is not None:       # each placement is classified
                print(f"lighting at {at}: label "
                      f"auto -> {r['meta']['label']} (p(outdoor) {r['meta']['p_outdoor']:.2f})")
            paths = write_outputs(r, Path(args.out) / "env" / f"{name}_estimate" / f"{name}.exr")
            print(f"lighting of {name!r} at {at}: {paths['json']}, {paths['preview']}")
            return r["hdr"]
    s = compose(args.scene_run, objects, args.placement, args.out, env=args.env,
                estimator=estimator, cfg=cfg, progress=not args.quiet)
    t = s["timings"]
    print(f"{'part':<20}{'seconds':>10}")
    for k in ("lighting", "probe_placement", "occlusion_tracing", "total"):
        print(f"{k:<20}{t[k]:>10.2f}")
    pr = s["pairs"]
    short = {n: c for n, c in s["probes"].get("shadow_per_object", {}).items()
             if c < cfg.shadow.count}                  # every facing scene point is used
    for n, c in short.items():
        print(f"shadow probes of {n!r}: {c} of the {cfg.shadow.count} asked (every scene "
              f"surface point facing it in its region has one)")
    print(f"{s['probes']['shadow']} shadow probes; occlusion pairs traced {len(pr['traced'])}, "
          f"reused {len(pr['reused'])}, culled {len(pr['culled'])}; wrote {args.out}")
    return 0


def _add_render_comp(sub) -> None:
    p = sub.add_parser(
        "render-comp", help="render a composition along NeRF-synthetic cameras or a "
                            "dataset's test views",
        description="Render COMP_DIR (from `comgs compose`) along the cameras of a "
                    "NeRF-synthetic transforms.json (the scene dataset's frame), or the test "
                    "views of a dataset folder or poses_bounds.npy (COLMAP, LLFF, "
                    "NeRF-synthetic, loaded as step 1 loads it), into "
                    "COMP_DIR/renders/<variant>/ and, with "
                    "--gt-dir, score against GT_DIR/<basename>.png into "
                    "COMP_DIR/metrics_<variant>.json (psnr, ssim, frame_seconds, per frame).")
    p.add_argument("comp_dir", metavar="COMP_DIR")
    p.add_argument("--cameras", required=True, metavar="transforms.json|DATASET",
                   help="a NeRF-synthetic transforms*.json, or a dataset folder (or its "
                        "poses_bounds.npy): its test views, every view if it has none")
    p.add_argument("--variant", choices=RENDER_VARIANTS, default="sop",
                   help="sop (cached shadows), trace (traced per frame), noshadow, paste")
    p.add_argument("--gt-dir", metavar="DIR", help="ground-truth PNGs named like the frames")
    p.add_argument("--material", action="append", default=[],
                   metavar="NAME:albedo=R,G,B,roughness=X,metallic=Y",
                   help="override an object's material (repeatable; not with --variant "
                        "paste): albedo=R,G,B (linear, in [0, 1]) or scale=S[,S,S] "
                        "(multiplies the albedo), roughness=X, metallic=Y")
    p.add_argument("--res", type=int, nargs="+", metavar=("W", "H"),
                   help="image size (default: the ground truth's, else the camera file's w/h)")
    p.add_argument("--rays", type=int, metavar="N", help="S_r (default 256)")
    p.add_argument("--variant-mitsuba", dest="mi_variant", default="auto", metavar="MITSUBA_VARIANT",
                   help="Mitsuba variant: auto (default), llvm_ad_rgb (CPU) or cuda_ad_rgb "
                        "(--variant is the composite variant)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_render_comp)


def _cmd_render_comp(args) -> int:
    set_variant(args.mi_variant)
    mats = {}
    if args.material and args.variant == "paste":
        raise ValueError("--material does not apply to --variant paste (it shows the objects' "
                         "captured radiance); use sop, trace or noshadow")
    for spec in args.material:
        name, sep, rest = spec.partition(":")
        if not sep:
            raise ValueError(f"--material expects NAME:albedo=..., got {spec!r}")
        parse_material_spec(rest)            # validate now, with a clear error
        mats[name] = rest
    res = None
    if args.res:
        if len(args.res) > 2:
            raise ValueError("--res takes W or W H")
        res = args.res[0] if len(args.res) == 1 else tuple(args.res)
    s = render_comp(args.comp_dir, args.cameras, args.variant, args.gt_dir, mats, res,
                    args.rays, progress=not args.quiet)
    line = (f"{s['frames']} frame(s) ({s['variant']}), first {s['first_frame_seconds']:.2f} s "
            f"(kernel compilation included)" + (f", then {s['frame_seconds']:.3f} s/frame "
                                                  f"(median)" if s["frames"] > 1 else ""))
    if "psnr" in s:
        line += f", PSNR {s['psnr']:.2f} dB, SSIM {s['ssim']:.4f}"
    print(line + f"; renders in {s['renders']}")
    return 0
