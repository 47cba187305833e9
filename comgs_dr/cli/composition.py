"""The command line: ``comgs compose``, ``render-comp``.

Each command takes its flags from its config dataclasses (``cli._flags.add_config_flags``)
and the shared ``--out``/``--mitsuba-variant``/``--quiet`` from ``core.config.shared_options``;
the tables below only say where a flag is spelled differently from its field. The stages
check the values; an error there exits 2 with its message (``cli.main``).
"""
from __future__ import annotations

import argparse

from comgs_dr import set_variant
from comgs_dr.cli._flags import Spelling, add_config_flags, field_overrides, preset_differences
from comgs_dr.core.config import shared_options
from comgs_dr.data.exposure import resolve_exposure
from comgs_dr.lighting.scene_label import LABEL_CHOICES
from comgs_dr.stages.compose import PRESETS as COMPOSE_PRESETS
from comgs_dr.stages.compose import ComposeConfig, compose, compose_config, summary_text
from comgs_dr.stages.estimate_light import PlacementEstimateConfig, placement_estimator
from comgs_dr.stages.render_comp import VARIANTS as RENDER_VARIANTS
from comgs_dr.stages.render_comp import RenderCompConfig, render_comp, summary_line

# ----------------------------------------------------------------------------- compose

ESTIMATION_FLAGS = {
    "label": Spelling(choices=LABEL_CHOICES, help="scene label of the lighting estimation "
                      "(auto: classified from the traced panorama; not with --env)"),
    "sun_from_shadows": Spelling(choices=("auto", "off"), help="auto: a sun the scene capture "
                                 "did not see is fitted to the scene's cast shadows "
                                 "(lighting.sun_fit); off: the panorama alone; not with --env"),
    "unseen_sky": Spelling(choices=("clear", "completion"), help="when a sun is fitted to the "
                           "shadows, the sky the capture did not see: clear (a clear sky for "
                           "that sun, lighting.clear_sky) or the completion's guess; not with "
                           "--env"),
    "sky_turbidity": Spelling(help="that clear sky's turbidity, [1, 10]; 0: from the "
                              "shadows' sun/sky ratio; not with --env"),
    "max_ground_albedo": Spelling(help="the unseen sky (with that sun, or with no sun where "
                                  "the capture barely saw the sky) is raised until the ground "
                                  "below reflects at most this of the light above (0: off); "
                                  "not with --env"),
    "weights": Spelling(metavar="W.pt", help="completion-net checkpoint of the estimation "
                        "(None: the shipped one; not with --env)"),
    "light_head": Spelling(metavar="HEAD.pt", help="light head of the estimation: a file, "
                           "none, or default (the shipped one); not with --env"),
    "scene_label": Spelling(metavar="M.json", help="the classifier of label auto (default: "
                            "the shipped one; e.g. from `comgs train-scene-label`; not with "
                            "--env)"),
}


def _add_compose(sub) -> None:
    p = sub.add_parser(
        "compose", parents=[shared_options(out=dict(required=True, metavar="COMP_DIR"))],
        help="edit stage: place objects in a scene, light them, cache occlusion",
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
    # the inputs (not settings)
    p.add_argument("scene_run", metavar="SCENE_RUN", help="`comgs reconstruct` folder of the scene")
    p.add_argument("--object", action="append", required=True, metavar="NAME=OBJECT_RUN",
                   help="an object: its name in transform.json and its `comgs decompose` "
                        "folder (or the reconstruct folder holding material/); repeatable")
    p.add_argument("--placement", required=True, metavar="transform.json")
    p.add_argument("--env", metavar="MAP", help="map lighting every object (default: estimate)")
    # not ComposeConfig fields: the preset is the config the flags then override, and
    # --shadow-probes sets the count of its nested ShadowConfig
    p.add_argument("--preset", choices=sorted(COMPOSE_PRESETS), default="default",
                   help="default: 10k shadow probes per object (paper), 32² texels; fast: "
                        "2k at 16² (20x fewer occlusion rays; shadows softer and "
                        "weaker, most under a low sun)")
    p.add_argument("--shadow-probes", type=int, metavar="N", help="shadow probes per object")
    add_config_flags(p, ComposeConfig,
                     presets=preset_differences(COMPOSE_PRESETS, ComposeConfig()))
    add_config_flags(p, PlacementEstimateConfig, ESTIMATION_FLAGS)
    _add_exposure_flags(p)
    p.set_defaults(func=_cmd_compose)


def _add_exposure_flags(p) -> None:
    """How the object's capture's exposure and white balance meet the scene's
    (``data.exposure``; docs/exposure.md). None given: gain 1, assumed and said so."""
    g = p.add_argument_group(
        "exposure and white balance (the object's photos vs the scene's; default gain 1, "
        "assumed: see docs/exposure.md)").add_mutually_exclusive_group()
    g.add_argument("--exposure-gain", dest="exposure_gain", nargs=3, type=float, default=None,
                   metavar=("R", "G", "B"),
                   help="scene-capture linear units per object-capture unit; multiplies each "
                        "object's albedo")
    g.add_argument("--white-patch", dest="white_patch", nargs=2, default=None,
                   metavar=("OBJECT_PHOTO[:X0,Y0,X1,Y1]", "SCENE_PHOTO[:X0,Y0,X1,Y1]"),
                   help="one reference surface (a grey card, the floor the object stood on) in "
                        "a photo of the object's capture and one of the scene's, lit alike: "
                        "gain = its linear colour in the scene photo / in the object photo")
    g.add_argument("--grey-world", dest="grey_world", action="store_true",
                   help="white balance only, from each object's mean albedo taken to be grey "
                        "(a coloured object is made grey on average)")


def _cmd_compose(args) -> int:
    set_variant(args.mitsuba_variant)
    objects = _object_runs(args.object)
    cfg = compose_config(args.preset, args.shadow_probes, **field_overrides(args, ComposeConfig))
    # the object -> scene gain (data.exposure); None: compose's default (gain 1, assumed)
    exposure = ("grey-world" if args.grey_world else
                resolve_exposure(args.exposure_gain, args.white_patch)
                if args.exposure_gain is not None or args.white_patch is not None else None)
    estimator = placement_estimator(args.scene_run, args.out, args.env, say=print,
                                    **field_overrides(args, PlacementEstimateConfig))
    s = compose(args.scene_run, objects, args.placement, args.out, env=args.env,
                estimator=estimator, cfg=cfg, progress=not args.quiet,
                **({"exposure": exposure} if exposure is not None else {}))
    print(summary_text(s, cfg, args.out))
    for name, e in s.get("exposure", {}).items():
        print(f"{name}: exposure gain {e['gain']} ({e['method']}, {e['exposure_ev']:+.2f} EV); "
              f"assumed: {e['assumed']}")
    return 0


def _object_runs(specs: list[str]) -> dict:
    """{name: object run} of the ``--object NAME=OBJECT_RUN`` values."""
    objects = {}
    for spec in specs:
        name, sep, run = spec.partition("=")
        if not sep or not name or not run:
            raise ValueError(f"--object expects NAME=OBJECT_RUN, got {spec!r}")
        if name in objects:
            raise ValueError(f"--object {name!r} given twice")
        objects[name] = run
    return objects


# ----------------------------------------------------------------------------- render-comp

RENDER_COMP_FLAGS = {
    "variant": Spelling(choices=RENDER_VARIANTS, help="sop (cached shadows), trace (traced "
                        "per frame), noshadow, paste"),
    "res": Spelling(nargs="+", type=int, metavar=("W", "H"), help="image size (None: the "
                    "ground truth's, else the camera file's w/h)"),
    "rays": Spelling(metavar="N", help="S_r, rays per pixel (None: the integrator's 256)"),
    "path": Spelling(metavar="orbit|spiral|FILE", help="render a camera path, not capture "
                     "views: orbit (a circle around the placed objects at the capture "
                     "cameras' mean distance and elevation), spiral (its height and distance "
                     "swinging) or a NeRF transforms.json; frames path_0000.png ..., no "
                     "ground truth; placed by --cameras, else the scene run's dataset"),
    "frames": Spelling(metavar="N", help="path frames (None: 60, or the file's count)"),
    "video": Spelling(metavar="OUT.mp4", help="also write the frames as an mp4 "
                      "(imageio-ffmpeg)"),
    "fps": Spelling(metavar="FPS", help="frames per second of --video"),
}


def _add_render_comp(sub) -> None:
    # --variant is the composite variant here: the Mitsuba variant is --mitsuba-variant only
    p = sub.add_parser(
        "render-comp", parents=[shared_options(variant_alias=False)],
        help="render a composition along NeRF cameras, a dataset's test views or a path",
        description="Render COMP_DIR (from `comgs compose`) along the cameras of a "
                    "NeRF transforms.json (the scene dataset's frame; camera_angle_x or "
                    "fl_x/fl_y/cx/cy/w/h, top-level or per frame), or the test "
                    "views of a dataset folder or poses_bounds.npy (COLMAP, LLFF, "
                    "NeRF-synthetic, loaded as step 1 loads it, each image's intrinsics), "
                    "or a camera path (--path orbit|spiral|FILE --frames N [--video "
                    "out.mp4]), into COMP_DIR/renders/<variant>/ and, with "
                    "--gt-dir, score against GT_DIR/<basename>.png into "
                    "COMP_DIR/metrics_<variant>.json (psnr, ssim, frame_seconds, per frame).")
    # the inputs (not settings)
    p.add_argument("comp_dir", metavar="COMP_DIR")
    p.add_argument("--cameras", metavar="transforms.json|DATASET",
                   help="a NeRF transforms*.json, or a dataset folder (or its "
                        "poses_bounds.npy): its test views, every view if it has none "
                        "(required without --path; with it, the capture the path is "
                        "placed by)")
    p.add_argument("--gt-dir", metavar="DIR", help="ground-truth PNGs named like the frames")
    # the Mitsuba variant's old name here, kept for existing scripts
    p.add_argument("--variant-mitsuba", dest="mitsuba_variant", default="auto",
                   help=argparse.SUPPRESS)
    # RenderCompConfig.materials is a dict: each --material NAME:SPEC is one entry
    p.add_argument("--material", action="append", default=[],
                   metavar="NAME:albedo=R,G,B,roughness=X,metallic=Y",
                   help="override an object's material (repeatable; not with --variant "
                        "paste): albedo=R,G,B (linear, in [0, 1]) or scale=S[,S,S] "
                        "(multiplies the albedo), roughness=X, metallic=Y")
    add_config_flags(p, RenderCompConfig, RENDER_COMP_FLAGS)
    p.set_defaults(func=_cmd_render_comp)
    from comgs_dr.cli.batch import add_render_comp_ray   # its --ray/--shards/--num-cpus
    add_render_comp_ray(p)


def _cmd_render_comp(args) -> int:
    set_variant(args.mitsuba_variant)
    kw = field_overrides(args, RenderCompConfig)
    if "res" in kw and len(kw["res"]) == 1:          # --res W: a square W×W image
        kw["res"] = kw["res"][0]
    cfg = RenderCompConfig(materials=_materials(args.material), **kw)
    if args.cameras is None and cfg.path is None:
        raise ValueError("render-comp: give --cameras (a transforms.json or a dataset "
                         "folder) or --path orbit|spiral|FILE")
    s = render_comp(args.comp_dir, args.cameras, cfg.variant, args.gt_dir, cfg.materials,
                    cfg.res, cfg.rays, cfg.seed, progress=not args.quiet, path=cfg.path,
                    frames=cfg.frames, video=cfg.video, fps=cfg.fps)
    print(summary_line(s))
    return 0


def _materials(specs: list[str]) -> dict:
    """{object name: material spec} of the ``--material NAME:SPEC`` values (the specs are
    checked by ``RenderCompConfig.validate``)."""
    mats = {}
    for spec in specs:
        name, sep, rest = spec.partition(":")
        if not sep:
            raise ValueError(f"--material expects NAME:albedo=..., got {spec!r}")
        mats[name] = rest
    return mats
