"""The command line: ``comgs make-dataset``, ``comgs demo``, ``comgs report``."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from comgs_dr import set_variant
from comgs_dr.data.synthetic import ObjectDatasetConfig, make_object_dataset
from comgs_dr.data.procedural import scene_dataset_config
from comgs_dr.demo import PRESETS as DEMO_PRESETS
from comgs_dr.demo import run_demo

# ----------------------------------------------------------------------------- make-dataset

def _add_make_dataset(sub) -> None:
    p = sub.add_parser("make-dataset", help="render synthetic ground-truth datasets",
                       description="Render synthetic ground truth with Mitsuba's path tracer.")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    o = kinds.add_parser(
        "object", help="one object under an HDR env map (NeRF-synthetic folder)",
        description="Object dataset in the SynCom-Object protocol: random upper-hemisphere "
                    "training views, test views on three latitude circles, G-buffer ground "
                    "truth and relit test views. Omitted values use the defaults of "
                    "comgs_dr.data.synthetic.ObjectDatasetConfig.")
    o.add_argument("--mesh", metavar="M",
                   help="OBJ/PLY mesh (default: the shared Spot mesh, if present), or "
                        "'detail': the built-in stress object (a photo-textured sphere in a "
                        "cage of sub-pixel to 3 px rods, rings and a slotted sheet)")
    o.add_argument("--envmap", metavar="E",
                   help="HDR/EXR lighting (default: a shared training map)")
    o.add_argument("--out", required=True, metavar="DIR", help="output directory")
    o.add_argument("--views", type=int, dest="n_train", metavar="N",
                   help="training views (default 100)")
    o.add_argument("--test-views", type=int, dest="n_test", metavar="N",
                   help="test views (default 24)")
    o.add_argument("--res", type=int, dest="resolution", metavar="R",
                   help="image side in pixels (default 128)")
    o.add_argument("--spp", type=int, metavar="S", help="samples per pixel of training views "
                   "(default 64; test views use twice as many)")
    o.add_argument("--relight", nargs="*", metavar="MAP",
                   help="env maps for relit test views (default: the held-out shared maps; "
                        "give the flag alone for none)")
    o.add_argument("--seed", type=int, metavar="S", help="camera/noise seed (default 0)")
    o.add_argument("--no-texture", action="store_true", help="ignore the mesh texture")
    o.add_argument("--up", choices=("y", "z"), dest="up_axis", help="up axis of the mesh file "
                   "(default y)")
    o.add_argument("--rings", type=float, nargs="+", dest="train_rings_deg", metavar="ELEV",
                   help="training views evenly on these elevation rings (degrees; default: "
                        "random in the upper hemisphere)")
    o.add_argument("--fov", type=float, dest="fov_deg", metavar="DEG",
                   help="field of view in degrees (default 40)")
    o.add_argument("--radius", type=float, metavar="R",
                   help="camera distance from the object's centre (default: fit the view)")
    o.add_argument("--half-extent", type=float, dest="half_extent", metavar="H",
                   help="largest half side of the object's bounding box (default 1)")
    o.add_argument("--base-color", type=float, nargs=3, dest="base_color", metavar="C",
                   help="linear base colour without texture (default 0.6 0.6 0.6)")
    o.add_argument("--roughness", type=float, metavar="R", help="principled roughness (default 0.5)")
    o.add_argument("--sfm-points", type=int, dest="sfm_points", metavar="N",
                   help="also write points3d.ply: N SfM-like surface points (default 0: none)")
    o.add_argument("--variant", default="auto", help="Mitsuba variant (default auto)")
    o.add_argument("--quiet", action="store_true", help="no progress bars")
    sc = kinds.add_parser(
        "scene", help="the procedural table-top scene with SfM-like points (scene preset test)",
        description="A ground slab with four objects under a procedural sky, training views from "
                    "15-75 deg elevation and points3d.ply (surface points seen by >= 2 training "
                    "views, coloured, jittered: what COLMAP gives a capture). Reconstruct it "
                    "with `comgs reconstruct DIR --scene`.")
    sc.add_argument("--out", required=True, metavar="DIR", help="output directory")
    sc.add_argument("--views", type=int, default=60, dest="n_train", metavar="N")
    sc.add_argument("--test-views", type=int, default=12, dest="n_test", metavar="N")
    sc.add_argument("--res", type=int, default=96, dest="resolution", metavar="R")
    sc.add_argument("--points", type=int, default=20000, metavar="N", help="0: no points3d.ply")
    sc.add_argument("--seed", type=int, default=0, metavar="S")
    sc.add_argument("--variant", default="auto", help="Mitsuba variant (default auto)")
    sc.add_argument("--quiet", action="store_true", help="no progress bars")
    ll = kinds.add_parser(
        "llff", help="a forward-facing LLFF capture without a point cloud (poses_bounds.npy)",
        description="A hand-held forward-facing capture of a textured table-top (a backdrop "
                    "wall, a floor, a sphere, a box, a card, a pillar; constant sky and sun, or "
                    "--envmap MAP) on a jittered ROWS x COLS grid: poses_bounds.npy, images/ and images_<k>/, "
                    "meta.json, and no points (comgs_dr.data.llff_synthetic). Reconstruct it "
                    "with `comgs reconstruct DIR --scene -r K`.")
    ll.add_argument("--out", required=True, metavar="DIR", help="output directory")
    ll.add_argument("--rows", type=int, default=4, metavar="N")
    ll.add_argument("--cols", type=int, default=5, metavar="N")
    ll.add_argument("--width", type=int, default=800, metavar="W", help="images/ width")
    ll.add_argument("--height", type=int, default=600, metavar="H", help="images/ height")
    ll.add_argument("--downscale", type=int, nargs="*", default=[8], metavar="K",
                    help="images_<K>/ folders written beside images/ (default 8)")
    ll.add_argument("--spp", type=int, default=16, metavar="S")
    ll.add_argument("--seed", type=int, default=0, metavar="S")
    ll.add_argument("--variant", default="auto", help="Mitsuba variant (default auto)")
    ll.add_argument("--envmap", metavar="MAP", help="an equirect .hdr/.exr lights the scene "
                    "(Z-up) instead of the constant sky and sun, and is its sky")
    ll.add_argument("--envmap-scale", type=float, default=None, metavar="S", help="its "
                    "exposure (default: auto, the sky in range and a sun clipped)")
    ll.add_argument("--envmap-rotate", type=float, default=0.0, metavar="DEG", help="turn "
                    "the map about +Z by DEG (the views look along +Y: put its sun in view)")
    ll.add_argument("--no-backdrop", action="store_true", help="no backdrop wall: the views "
                    "see the map's horizon and sky")
    ll.add_argument("--pitch", type=float, default=0.0, metavar="DEG", help="tilt the cameras "
                    "up by DEG (more sky in view); the LLFF loader takes the mean camera up as "
                    "+Z, so the reconstruction's frame tilts by about as much (9.7 deg for 10)")
    ll.add_argument("--probe-height", type=int, default=0, metavar="H", help="write "
                    "probes/center.exr (H rows), the true light at the placement, and "
                    "probes/probes.json (its position in the reconstruction's frame)")
    ll.add_argument("--quiet", action="store_true", help="no per-view lines")
    c = kinds.add_parser(
        "composition", help="a scene, objects and path-traced composites of them (ground truth)",
        description="scene/ (NeRF-synthetic capture of a textured ground with a wall and a box, "
                    "no objects), objects/<name>/ (each object alone, as `make-dataset object`), "
                    "transform.json (placements on the ground) and comp/ (spiral test views: "
                    "gt/ with the objects really in the scene, empty/ without, mask/). Omitted "
                    "values use the defaults of comgs_dr.data.composition_dataset."
                    "CompositionDatasetConfig.")
    c.add_argument("--out", required=True, metavar="DIR", help="output directory")
    c.add_argument("--objects", metavar="LIST",
                   help="comma-separated shared object names (spot, teapot, suzanne) or .obj/.ply "
                        "paths (default spot,teapot)")
    c.add_argument("--scene-map", dest="scene_map", metavar="M",
                   help="HDR map of the scene and composites (shared name or path; default "
                        "blender_sunrise.exr)")
    c.add_argument("--object-map", dest="object_map", metavar="M",
                   help="HDR map of the object captures (default blender_studio.exr)")
    c.add_argument("--res", type=int, dest="resolution", metavar="R",
                   help="image side in pixels (default 96)")
    c.add_argument("--comp-res", type=int, dest="comp_resolution", metavar="R",
                   help="side of the composites (comp/: gt, empty, mask; default: --res)")
    c.add_argument("--scene-views", type=int, dest="scene_views", metavar="N",
                   help="scene training views (default 64)")
    c.add_argument("--object-views", type=int, dest="object_views", metavar="N",
                   help="training views per object (default 48)")
    c.add_argument("--test-views", type=int, dest="test_views", metavar="N",
                   help="test views of the scene, of each object and composites (default 8)")
    c.add_argument("--sky-views", type=int, dest="sky_views", metavar="N",
                   help="extra scene views from eye height looking out over the horizon, so the "
                        "capture sees the sky (default 0)")
    c.add_argument("--sun-view", action="store_true", dest="sun_view", default=None,
                   help="aim the first sky view at the sun (a low sun is then always seen)")
    c.add_argument("--probe-height", type=int, default=128, metavar="H",
                   help="rows of probes/<object>.exr, the true light at the centre of each "
                        "object's box (the scene without the objects, path-traced from there; "
                        "where `compose` estimates the lighting): the reference for a lighting "
                        "estimate (`comgs compare-light`); default 128, 0: none")
    c.add_argument("--ground-half", type=float, dest="ground_half", metavar="H",
                   help="half side of the square ground (default 25)")
    c.add_argument("--spp", type=int, metavar="S", help="samples per pixel of training views "
                   "(default 128; test views and composites use twice as many)")
    c.add_argument("--points", type=int, dest="sfm_points", metavar="N",
                   help="SfM-like points in scene/points3d.ply (default 10000; 0: none)")
    c.add_argument("--seed", type=int, metavar="S", help="camera/placement/noise seed (default 0)")
    c.add_argument("--variant", default="auto", help="Mitsuba variant (default auto)")
    c.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_make_dataset)


def _cmd_make_dataset(args) -> int:
    if args.kind == "object":
        return _make_object(args)
    if args.kind == "scene":
        return _make_scene(args)
    if args.kind == "composition":
        return _make_composition(args)
    if args.kind == "llff":
        return _make_llff(args)
    raise AssertionError(f"unhandled dataset kind {args.kind}")  # argparse restricts KIND


def _make_object(args) -> int:
    overrides = {k: getattr(args, k) for k in
                 ("mesh", "envmap", "n_train", "n_test", "resolution", "spp", "seed", "up_axis",
                  "sfm_points", "fov_deg", "radius", "half_extent", "roughness")
                 if getattr(args, k) is not None}
    if args.relight is not None:
        overrides["relight_envmaps"] = tuple(args.relight)
    if args.no_texture:
        overrides["texture"] = None
    if args.train_rings_deg:
        overrides["train_rings_deg"] = tuple(args.train_rings_deg)
    if args.base_color is not None:
        overrides["base_color"] = tuple(args.base_color)
    cfg = ObjectDatasetConfig(out_dir=args.out, variant=set_variant(args.variant), **overrides)
    s = make_object_dataset(cfg, progress=not args.quiet)
    relit = ", ".join(s["relight"]) or "none"
    print(f"wrote {s['n_train']} train + {s['n_test']} test views ({s['resolution']}px, "
          f"relit: {relit}) to {s['out_dir']} in {s['seconds']:.1f} s [{s['variant']}]")
    return 0


def _make_scene(args) -> int:
    if args.points < 0:
        raise SystemExit("comgs make-dataset scene: --points must be >= 0")
    cfg = scene_dataset_config(args.out, args.n_train, args.n_test, args.resolution, args.points,
                               args.seed)
    s = make_object_dataset(dataclasses.replace(cfg, variant=set_variant(args.variant)),
                            progress=not args.quiet)
    print(f"wrote {s['n_train']} train + {s['n_test']} test views ({s['resolution']}px) and "
          f"{args.points} points to {s['out_dir']} in {s['seconds']:.1f} s [{s['variant']}]")
    return 0


def _make_llff(args) -> int:
    from comgs_dr.data.llff_synthetic import LLFFDatasetConfig, make_llff_dataset
    for flag, v, lo in (("--rows", args.rows, 1), ("--cols", args.cols, 1),
                        ("--width", args.width, 8), ("--height", args.height, 8),
                        ("--spp", args.spp, 1)):
        if v < lo:
            raise ValueError(f"make-dataset llff: {flag} must be >= {lo}, got {v}")
    if args.rows * args.cols < 2:
        raise ValueError("make-dataset llff: need at least 2 views (--rows x --cols)")
    for flag, given in (("--envmap-scale", args.envmap_scale is not None),
                        ("--envmap-rotate", args.envmap_rotate != 0.0),
                        ("--probe-height", args.probe_height > 0)):
        if given and args.envmap is None:   # the default sun is a delta light no ray hits
            raise ValueError(f"make-dataset llff: {flag} needs --envmap")
    if args.envmap_scale is not None and not 0 < args.envmap_scale < float("inf"):
        raise ValueError(f"make-dataset llff: --envmap-scale must be > 0, got {args.envmap_scale}")
    if not -60.0 <= args.pitch <= 60.0:
        raise ValueError(f"make-dataset llff: --pitch must lie in [-60, 60] degrees, got "
                         f"{args.pitch}")
    if not 0 <= args.probe_height <= 1024:
        raise ValueError(f"make-dataset llff: --probe-height must lie in [0, 1024], got "
                         f"{args.probe_height}")
    if any(k < 1 or args.width % k or args.height % k for k in args.downscale):
        raise ValueError(f"make-dataset llff: each --downscale must be >= 1 and divide "
                         f"{args.width}x{args.height}, got {args.downscale}")
    small = [k for k in args.downscale if min(args.width, args.height) // k < 8]
    if small:
        raise ValueError(f"make-dataset llff: --downscale {small[0]} makes "
                         f"{args.width // small[0]}x{args.height // small[0]} images (under 8 "
                         f"px); give a smaller --downscale (the default is 8)")
    cfg = LLFFDatasetConfig(out_dir=args.out, rows=args.rows, cols=args.cols, width=args.width,
                            height=args.height, downscales=tuple(args.downscale), spp=args.spp,
                            seed=args.seed, variant=set_variant(args.variant),
                            envmap=args.envmap, envmap_scale=args.envmap_scale,
                            envmap_rotate_deg=args.envmap_rotate,
                            backdrop=not args.no_backdrop, pitch_deg=args.pitch,
                            probe_height=args.probe_height)
    m = make_llff_dataset(cfg, progress=not args.quiet)
    print(f"wrote {len(m['images'])} views ({len(m['test_images'])} of them LLFF test views), "
          f"{args.width}x{args.height} + images_{{{','.join(map(str, args.downscale))}}}, "
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
    from comgs_dr.data.composition_dataset import CompositionDatasetConfig, make_composition_dataset
    overrides = {k: getattr(args, k) for k in
                 ("objects", "scene_map", "object_map", "resolution", "scene_views", "object_views",
                  "test_views", "spp", "sfm_points", "seed", "sky_views", "ground_half",
                  "sun_view", "comp_resolution")
                 if getattr(args, k, None) is not None}
    from comgs_dr.data.placement_probe import MAX_HEIGHT, write_probes
    if not 0 <= args.probe_height <= MAX_HEIGHT:
        raise ValueError(f"--probe-height must be in [0, {MAX_HEIGHT}], got {args.probe_height}")
    cfg = CompositionDatasetConfig(out_dir=args.out, variant=set_variant(args.variant), **overrides)
    s = make_composition_dataset(cfg, progress=not args.quiet)
    if args.probe_height:
        probes = write_probes(args.out, args.probe_height)
        print(f"wrote {len(probes)} placement probe(s) ({args.probe_height} rows) to "
              f"{Path(args.out) / 'probes'}")
    sec = s["seconds"]
    print(f"wrote scene ({s['n_scene_train']} train views), objects {', '.join(s['objects'])} "
          f"({s['n_object_train']} train views each) and {s['n_test']} composite test views "
          f"({s['comp_resolution']}px; captures {s['resolution']}px) to {s['out_dir']} in "
          f"{sec['total']:.1f} s (scene {sec['scene']:.1f} s, objects {sum(sec['objects'].values()):.1f} s, composites "
          f"{sec['comp']:.1f} s) [{s['variant']}]")
    return 0


# ----------------------------------------------------------------------------- demo

def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the whole pipeline on embedded procedural inputs (no download)",
                       description="Procedural object, scene and maps -> path-traced ground truth -> "
                                   "object step 1 + step 2, scene step 1 -> lighting estimated at "
                                   "the placement -> occlusion cached in SOPs -> composition with "
                                   "SOP shadows, traced shadows and a naive paste, scored against "
                                   "the ground truth -> OUT/report.html (see comgs_dr.demo).")
    p.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    p.add_argument("--preset", choices=sorted(DEMO_PRESETS), default="default",
                   help="default: 128 px captures, 256 px composites, ~11 min on 2 cores; "
                        "tiny: a smoke test (~1 min)")
    p.add_argument("--res", type=int, help="side of the captures (default: the preset's)")
    p.add_argument("--comp-res", type=int, dest="comp_res",
                   help="side of the composition frames (default: the preset's)")
    p.add_argument("--object-light", choices=("learnt", "known"), default="learnt",
                   help="step 2 learns the object's capture light (default) or takes the known "
                        "studio map (decompose --env-file)")
    p.add_argument("--sky-views", type=int, dest="sky_views", metavar="N",
                   help="scene capture views over the horizon that see the sky and the sun "
                        "(default: the preset's; 0: a capture that never looks at the sun, "
                        "whose lighting must take the sun from the scene's shadows)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args) -> int:
    cfg = dataclasses.replace(DEMO_PRESETS[args.preset], out_dir=args.out, progress=not args.quiet,
                              object_light=args.object_light)
    if args.res is not None:
        cfg = dataclasses.replace(cfg, resolution=args.res)
    if args.sky_views is not None:
        cfg = dataclasses.replace(cfg, sky_views=args.sky_views)
    if args.comp_res is not None:
        cfg = dataclasses.replace(cfg, comp_resolution=args.comp_res)
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
    p = sub.add_parser("report", help="one self-contained HTML report of a run folder",
                       description="Plot every metrics.jsonl below RUN_DIR (error against wall "
                                   "time, per stage), tabulate the stage summaries and inline "
                                   "the pictures into one HTML file (default RUN_DIR/report.html).")
    p.add_argument("run", metavar="RUN_DIR")
    p.add_argument("--out", metavar="FILE.html")
    p.add_argument("--title")
    p.set_defaults(func=_cmd_report)


def _cmd_report(args) -> int:
    from comgs_dr.eval.report import write_report
    print(f"wrote {write_report(args.run, args.out, args.title)}")
    return 0
