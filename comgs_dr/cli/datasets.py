"""The command line: ``comgs make-dataset`` (object, scene, llff, composition), ``comgs demo``,
``comgs report``.

Each command takes its flags from its config dataclass (``cli._flags.add_config_flags``);
the tables below only say where a flag is spelled differently from its field.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from comgs_dr import set_variant
from comgs_dr.cli._flags import Spelling, add_config_flags, field_overrides, preset_differences
from comgs_dr.core.config import shared_options
from comgs_dr.data.composition_dataset import CompositionDatasetConfig, make_composition_dataset
from comgs_dr.data.llff_synthetic import LLFFDatasetConfig, make_llff_dataset
from comgs_dr.data.placement_probe import write_probes
from comgs_dr.data.procedural import scene_dataset_config
from comgs_dr.data.synthetic import ObjectDatasetConfig, SceneDatasetConfig, make_object_dataset
from comgs_dr.demo import OBJECT_LIGHTS, DemoConfig, run_demo
from comgs_dr.demo import PRESETS as DEMO_PRESETS
from comgs_dr.eval.report import ReportConfig, write_report

_DIR_OUT = dict(required=True, metavar="DIR", help="output directory")
_SET_BY_COMMAND = ("out_dir", "variant")          # from --out and --mitsuba-variant

# ----------------------------------------------------------------------------- make-dataset

OBJECT_FLAGS = {
    "mesh": Spelling(type=str, metavar="M", help="OBJ/PLY mesh, or 'detail': the built-in "
                     "stress object (a photo-textured sphere in a cage of sub-pixel to 3 px "
                     "rods, rings and a slotted sheet); None: the shared Spot mesh"),
    "envmap": Spelling(type=str, metavar="E", help="HDR/EXR lighting; None: a shared "
                       "training map"),
    "n_train": Spelling(("--views",), metavar="N", help="training views"),
    "n_test": Spelling(("--test-views",), metavar="N", help="test views"),
    "resolution": Spelling(("--res",), metavar="R", help="image side in pixels"),
    "spp": Spelling(metavar="S", help="samples per pixel of training views (test views: "
                    "twice as many unless --spp-test)"),
    "relight_envmaps": Spelling(("--relight",), type=str, nargs="*", metavar="MAP",
                                help="env maps of relit test views (None: the held-out "
                                     "shared maps; the flag alone: none)"),
    "seed": Spelling(metavar="S", help="camera/noise seed"),
    "texture": Spelling(("--no-texture",), const=None, help="ignore the mesh texture"),
    "up_axis": Spelling(("--up",), choices=("y", "z"), help="up axis of the mesh file"),
    "train_rings_deg": Spelling(("--rings",), nargs="+", metavar="ELEV",
                                help="training views evenly on these elevation rings "
                                     "(degrees; none: random in the upper hemisphere)"),
    "fov_deg": Spelling(("--fov",), metavar="DEG", help="field of view in degrees"),
    "radius": Spelling(metavar="R", help="camera distance from the object's centre (None: "
                       "fit the view)"),
    "half_extent": Spelling(metavar="H", help="largest half side of the object's box"),
    "base_color": Spelling(nargs=3, metavar="C", help="linear base colour without texture"),
    "roughness": Spelling(metavar="R", help="principled roughness"),
    "sfm_points": Spelling(metavar="N", help="also write points3d.ply: N SfM-like surface "
                           "points (0: none)"),
}
SCENE_FLAGS = {
    "n_train": Spelling(("--views",), metavar="N", help="training views"),
    "n_test": Spelling(("--test-views",), metavar="N", help="test views"),
    "resolution": Spelling(("--res",), metavar="R", help="image side in pixels"),
    "points": Spelling(metavar="N", help="SfM-like points (0: no points3d.ply)"),
    "seed": Spelling(metavar="S"),
}
LLFF_FLAGS = {
    "rows": Spelling(metavar="N"),
    "cols": Spelling(metavar="N"),
    "width": Spelling(metavar="W", help="images/ width"),
    "height": Spelling(metavar="H", help="images/ height"),
    "downscales": Spelling(("--downscale",), nargs="*", metavar="K",
                           help="images_<K>/ folders written beside images/"),
    "spp": Spelling(metavar="S"),
    "seed": Spelling(metavar="S"),
    "envmap": Spelling(metavar="MAP", help="an equirect .hdr/.exr lights the scene (Z-up) "
                       "instead of the constant sky and sun, and is its sky"),
    "envmap_scale": Spelling(metavar="S", help="its exposure (None: auto, the sky in range "
                             "and a sun clipped)"),
    "envmap_rotate_deg": Spelling(("--envmap-rotate",), metavar="DEG", help="turn the map "
                                  "about +Z by DEG (the views look along +Y: put its sun in "
                                  "view)"),
    "backdrop": Spelling(("--no-backdrop",), const=False, help="no backdrop wall: the views "
                         "see the map's horizon and sky"),
    "pitch_deg": Spelling(("--pitch",), metavar="DEG", help="tilt the cameras up by DEG (more "
                          "sky in view); the LLFF loader takes the mean camera up as +Z, so "
                          "the reconstruction's frame tilts by about as much"),
    "probe_height": Spelling(metavar="H", help="write probes/center.exr (H rows), the true "
                             "light at the placement, and probes/probes.json (its position "
                             "in the reconstruction's frame)"),
}
COMPOSITION_FLAGS = {
    "objects": Spelling(type=str, metavar="LIST", help="comma-separated shared object names "
                        "(spot, teapot, suzanne) or .obj/.ply paths"),
    "scene_map": Spelling(type=str, metavar="M", help="HDR map of the scene and composites "
                          "(shared name or path)"),
    "object_map": Spelling(type=str, metavar="M", help="HDR map of the object captures"),
    "resolution": Spelling(("--res",), metavar="R", help="image side in pixels"),
    "comp_resolution": Spelling(("--comp-res",), metavar="R", help="side of the composites "
                                "(comp/: gt, empty, mask; None: --res)"),
    "scene_views": Spelling(metavar="N", help="scene training views"),
    "object_views": Spelling(metavar="N", help="training views per object"),
    "test_views": Spelling(metavar="N", help="test views of the scene, of each object and "
                           "composites"),
    "sky_views": Spelling(metavar="N", help="extra scene views from eye height looking out "
                          "over the horizon, so the capture sees the sky"),
    "sun_view": Spelling(("--sun-view",), const=True, help="aim the first sky view at the "
                         "sun (a low sun is then always seen)"),
    "probe_height": Spelling(metavar="H", help="rows of probes/<object>.exr, the true light "
                             "at the centre of each object's box (the scene without the "
                             "objects, path-traced from there; where `compose` estimates the "
                             "lighting): the reference of `comgs compare-light`; 0: none"),
    "ground_half": Spelling(metavar="H", help="half side of the square ground"),
    "ground_tint": Spelling(nargs=3, metavar="T", help="sRGB multipliers of the ground's gravel "
                            "texture, clipped to 1 (1.25 1.25 1.2: a pale, sand- or "
                            "concrete-like ground)"),
    "spp": Spelling(metavar="S", help="samples per pixel of training views (test views and "
                    "composites: twice as many unless --spp-test)"),
    "sfm_points": Spelling(("--points",), metavar="N", help="SfM-like points in "
                           "scene/points3d.ply (0: none)"),
    "seed": Spelling(metavar="S", help="camera/placement/noise seed"),
}


def _add_make_dataset(sub) -> None:
    p = sub.add_parser("make-dataset", help="render synthetic ground-truth datasets",
                       description="Render synthetic ground truth with Mitsuba's path tracer.")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    for add in (_add_make_object, _add_make_scene, _add_make_llff, _add_make_composition):
        add(kinds)
    p.set_defaults(func=_cmd_make_dataset)


def _add_make_object(kinds) -> None:
    p = kinds.add_parser(
        "object", parents=[shared_options(out=_DIR_OUT)],
        help="one object under an HDR env map (NeRF-synthetic folder)",
        description="Object dataset in the SynCom-Object protocol: random upper-hemisphere "
                    "training views, test views on three latitude circles, G-buffer ground "
                    "truth and relit test views (comgs_dr.data.synthetic.ObjectDatasetConfig).")
    add_config_flags(p, ObjectDatasetConfig, OBJECT_FLAGS, exclude=_SET_BY_COMMAND)


def _add_make_scene(kinds) -> None:
    p = kinds.add_parser(
        "scene", parents=[shared_options(out=_DIR_OUT)],
        help="the procedural table-top scene with SfM-like points (scene preset test)",
        description="A ground slab with four objects under a procedural sky, training views from "
                    "15-75 deg elevation and points3d.ply (surface points seen by >= 2 training "
                    "views, coloured, jittered: what COLMAP gives a capture). Reconstruct it "
                    "with `comgs reconstruct DIR --scene`.")
    add_config_flags(p, SceneDatasetConfig, SCENE_FLAGS)


def _add_make_llff(kinds) -> None:
    p = kinds.add_parser(
        "llff", parents=[shared_options(out=_DIR_OUT)],
        help="a forward-facing LLFF capture without a point cloud (poses_bounds.npy)",
        description="A hand-held forward-facing capture of a textured table-top (a backdrop "
                    "wall, a floor, a sphere, a box, a card, a pillar; constant sky and sun, or "
                    "--envmap MAP) on a jittered ROWS x COLS grid: poses_bounds.npy, images/ and "
                    "images_<k>/, meta.json, and no points (comgs_dr.data.llff_synthetic). "
                    "Reconstruct it with `comgs reconstruct DIR --scene -r K`.")
    add_config_flags(p, LLFFDatasetConfig, LLFF_FLAGS, exclude=_SET_BY_COMMAND)


def _add_make_composition(kinds) -> None:
    p = kinds.add_parser(
        "composition", parents=[shared_options(out=_DIR_OUT)],
        help="a scene, objects and path-traced composites of them (ground truth)",
        description="scene/ (NeRF-synthetic capture of a textured ground with a wall and a box, "
                    "no objects), objects/<name>/ (each object alone, as `make-dataset object`), "
                    "transform.json (placements on the ground), comp/ (spiral test views: "
                    "gt/ with the objects really in the scene, empty/ without, mask/) and "
                    "probes/ (comgs_dr.data.composition_dataset.CompositionDatasetConfig).")
    add_config_flags(p, CompositionDatasetConfig, COMPOSITION_FLAGS, exclude=_SET_BY_COMMAND)


def _cmd_make_dataset(args) -> int:
    makers = {"object": _make_object, "scene": _make_scene, "llff": _make_llff,
              "composition": _make_composition}
    return makers[args.kind](args)                     # argparse restricts KIND


def _make_object(args) -> int:
    cfg = ObjectDatasetConfig(out_dir=args.out, variant=set_variant(args.mitsuba_variant),
                              **field_overrides(args, ObjectDatasetConfig))
    s = make_object_dataset(cfg, progress=not args.quiet)
    relit = ", ".join(s["relight"]) or "none"
    print(f"wrote {s['n_train']} train + {s['n_test']} test views ({s['resolution']}px, "
          f"relit: {relit}) to {s['out_dir']} in {s['seconds']:.1f} s [{s['variant']}]")
    return 0


def _make_scene(args) -> int:
    sc = SceneDatasetConfig(**field_overrides(args, SceneDatasetConfig))
    cfg = scene_dataset_config(args.out, sc.n_train, sc.n_test, sc.resolution, sc.points,
                               sc.seed)
    s = make_object_dataset(dataclasses.replace(cfg, variant=set_variant(args.mitsuba_variant)),
                            progress=not args.quiet)
    print(f"wrote {s['n_train']} train + {s['n_test']} test views ({s['resolution']}px) and "
          f"{sc.points} points to {s['out_dir']} in {s['seconds']:.1f} s [{s['variant']}]")
    return 0


def _make_llff(args) -> int:
    cfg = LLFFDatasetConfig(out_dir=args.out, variant=set_variant(args.mitsuba_variant),
                            **field_overrides(args, LLFFDatasetConfig))
    m = make_llff_dataset(cfg, progress=not args.quiet)
    print(f"wrote {len(m['images'])} views ({len(m['test_images'])} of them LLFF test views), "
          f"{cfg.width}x{cfg.height} + images_{{{','.join(map(str, cfg.downscales))}}}, "
          f"poses_bounds.npy, no points, to {args.out} in {m['seconds']:.1f} s")
    if m["probe"] is not None:
        x, y, z = m["probe"]["position"]
        wx, wy, wz = m["probe"]["position_world"]
        print(f"true light at the placement: {m['probe']['file']}; estimate it with "
              f"`comgs estimate-light RUN/point_cloud.ply --at {x:.3f} {y:.3f} {z:.3f} ...` "
              f"(the reconstruction's frame) and score with `comgs compare-light EST.exr "
              f"{m['probe']['file']}`; a `compose` placement there is {wx:g} {wy:g} {wz:g} "
              f"(placements are in the dataset's frame)")
    return 0


def _make_composition(args) -> int:
    cfg = CompositionDatasetConfig(out_dir=args.out, variant=set_variant(args.mitsuba_variant),
                                   **field_overrides(args, CompositionDatasetConfig))
    s = make_composition_dataset(cfg, progress=not args.quiet)
    if cfg.probe_height:
        probes = write_probes(args.out, cfg.probe_height)
        print(f"wrote {len(probes)} placement probe(s) ({cfg.probe_height} rows) to "
              f"{Path(args.out) / 'probes'}")
    sec = s["seconds"]
    print(f"wrote scene ({s['n_scene_train']} train views), objects {', '.join(s['objects'])} "
          f"({s['n_object_train']} train views each) and {s['n_test']} composite test views "
          f"({s['comp_resolution']}px; captures {s['resolution']}px) to {s['out_dir']} in "
          f"{sec['total']:.1f} s (scene {sec['scene']:.1f} s, objects "
          f"{sum(sec['objects'].values()):.1f} s, composites {sec['comp']:.1f} s) [{s['variant']}]")
    return 0


# ----------------------------------------------------------------------------- demo, report

DEMO_FLAGS = {
    "resolution": Spelling(("--res",), metavar="R", help="side of the captures"),
    "comp_resolution": Spelling(("--comp-res",), metavar="R", help="side of the composition "
                                "frames (None: the captures')"),
    "object_light": Spelling(choices=OBJECT_LIGHTS, help="step 2 learns the object's capture "
                             "light (learnt) or takes the known studio map (known: "
                             "decompose --env-file)"),
    "sky_views": Spelling(metavar="N", help="scene capture views over the horizon that see "
                          "the sky and the sun (0, the default: a capture that never looks at "
                          "the sun, whose lighting takes the sun from the scene's shadows; 12: "
                          "one that saw it)"),
}


def _add_demo(sub) -> None:
    p = sub.add_parser(
        "demo", parents=[shared_options(out=dict(default=None, metavar="DIR", help=(
            f"output directory (default {DemoConfig.out_dir})")), mitsuba_variant=False)],
        help="the whole pipeline on embedded procedural inputs (no download)",
        description="Procedural object, scene and maps -> path-traced ground truth -> "
                    "object step 1 + step 2, scene step 1 -> lighting estimated at "
                    "the placement -> occlusion cached in SOPs -> composition with "
                    "SOP shadows, traced shadows and a naive paste, scored against "
                    "the ground truth -> OUT/report.html (see comgs_dr.demo).")
    # not a DemoConfig field: the preset is the config the flags then override
    p.add_argument("--preset", choices=sorted(DEMO_PRESETS), default="default",
                   help="default: 128 px captures, 256 px composites, ~11 min on 2 cores; "
                        "tiny: a smoke test (~1 min)")
    add_config_flags(p, DemoConfig, DEMO_FLAGS, exclude=("out_dir", "progress"),
                     presets=preset_differences(DEMO_PRESETS, DemoConfig()))
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args) -> int:
    given = {"out_dir": args.out} if args.out is not None else {}
    cfg = dataclasses.replace(DEMO_PRESETS[args.preset], progress=not args.quiet, **given,
                              **field_overrides(args, DemoConfig))
    s = run_demo(cfg)
    print(f"[{s['variant']}] composition of {s['frames']} test frames against path-traced ground "
          f"truth ({cfg.comp_resolution or cfg.resolution}px; captures {cfg.resolution}px):")
    print(f"{'variant':<10}{'PSNR':>8}{'SSIM':>8}{'s/frame':>10}")
    for v, m in s["composition"].items():
        print(f"{v:<10}{m['psnr']:>8.2f}{m['ssim']:>8.4f}{m['frame_seconds']:>10.3f}")
    print(f"SOP better than paste on {s['sop_beats_paste_frames']}/{s['frames']} frames; total "
          f"{s['total_seconds']:.0f} s; report: {s['report']}")
    return 0


def _add_report(sub) -> None:
    p = sub.add_parser(
        "report", parents=[shared_options(out=dict(metavar="FILE.html", help="output file "
                                                   "(default RUN_DIR/report.html)"),
                                          mitsuba_variant=False, quiet=False)],
        help="one self-contained HTML report of a run folder",
        description="Plot every metrics.jsonl below RUN_DIR (error against wall "
                    "time, per stage), tabulate the stage summaries and inline "
                    "the pictures into one HTML file (default RUN_DIR/report.html).")
    p.add_argument("run", metavar="RUN_DIR")
    add_config_flags(p, ReportConfig, {"title": Spelling(metavar="TITLE")})
    p.set_defaults(func=_cmd_report)


def _cmd_report(args) -> int:
    cfg = ReportConfig(**field_overrides(args, ReportConfig))
    print(f"wrote {write_report(args.run, args.out, cfg.title)}")
    return 0
