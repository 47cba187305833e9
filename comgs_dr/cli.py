"""The ``comgs`` command line.

Each subcommand has a parser builder ``_add_<name>(subparsers)`` (listed in
``_SUBCOMMANDS``) that sets ``func=_cmd_<name>``; ``_cmd_<name>(args)`` returns an exit
code. Heavy modules are imported inside the ``_cmd_`` functions.

    comgs make-dataset object --mesh M --envmap E --out DIR [--views N] [--test-views N]
                              [--res R] [--spp S] [--relight MAP ...] [--seed S] [--variant V]
                              [--sfm-points N]
    comgs make-dataset scene --out DIR [--views 60] [--res 96] [--points 20000]
    comgs estimate-light SCENE.ply --at X Y Z --out ENV.exr [--label L] [--width W]
                              [--height H] [--exclude-radius R] [--backend B] [--weights PATH]
                              [--diffusers-dir DIR]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from comgs_dr import set_variant
from comgs_dr.core.config import add_config_arguments, config_overrides, numeric_problem
from comgs_dr.data.load import load_dataset
from comgs_dr.data.synthetic import ObjectDatasetConfig, make_object_dataset
from comgs_dr.data.procedural import scene_dataset_config
from comgs_dr.demo import PRESETS as DEMO_PRESETS
from comgs_dr.demo import run_demo
from comgs_dr.lighting import backends
from comgs_dr.shading.shade import SAMPLINGS
from comgs_dr.shading.visibility import KINDS
from comgs_dr.stages import train_completion
from comgs_dr.stages import train_light_head
from comgs_dr.stages.compose import PRESETS as COMPOSE_PRESETS
from comgs_dr.stages.compose import compose
from comgs_dr.stages.decompose import MaterialConfig, train_material
from comgs_dr.stages.export_mesh import METHODS as MESH_METHODS
from comgs_dr.stages.export_mesh import PRESETS as MESH_PRESETS
from comgs_dr.stages.export_mesh import MeshConfig, export_mesh
from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light, write_outputs
from comgs_dr.stages.reconstruct import (
    PRESETS as RECON_PRESETS,
    RadianceConfig,
    scaled_density_schedule,
    train_radiance,
)
from comgs_dr.stages.relight import relight_run
from comgs_dr.stages.render_comp import VARIANTS as RENDER_VARIANTS
from comgs_dr.stages.render_comp import render_comp
from comgs_dr.stages.render_run import render_run
from comgs_dr.surfels.edit import parse_mask_spec, parse_material_spec
from comgs_dr.train.interrupt import TrainingInterrupted
from comgs_dr.train.run import write_run_info

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
    c.add_argument("--scene-views", type=int, dest="scene_views", metavar="N",
                   help="scene training views (default 64)")
    c.add_argument("--object-views", type=int, dest="object_views", metavar="N",
                   help="training views per object (default 48)")
    c.add_argument("--test-views", type=int, dest="test_views", metavar="N",
                   help="test views of the scene, of each object and composites (default 8)")
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


def _make_composition(args) -> int:
    from comgs_dr.data.composition_dataset import CompositionDatasetConfig, make_composition_dataset
    overrides = {k: getattr(args, k) for k in
                 ("objects", "scene_map", "object_map", "resolution", "scene_views", "object_views",
                  "test_views", "spp", "sfm_points", "seed") if getattr(args, k) is not None}
    cfg = CompositionDatasetConfig(out_dir=args.out, variant=set_variant(args.variant), **overrides)
    s = make_composition_dataset(cfg, progress=not args.quiet)
    sec = s["seconds"]
    print(f"wrote scene ({s['n_scene_train']} train views), objects {', '.join(s['objects'])} "
          f"({s['n_object_train']} train views each) and {s['n_test']} composite test views "
          f"({s['resolution']}px) to {s['out_dir']} in {sec['total']:.1f} s (scene "
          f"{sec['scene']:.1f} s, objects {sum(sec['objects'].values()):.1f} s, composites "
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
                   help="default: a few minutes on 2 cores; tiny: a smoke test (~1 min)")
    p.add_argument("--res", type=int, help="image side (default: the preset's)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args) -> int:
    cfg = dataclasses.replace(DEMO_PRESETS[args.preset], out_dir=args.out, progress=not args.quiet)
    if args.res is not None:
        cfg = dataclasses.replace(cfg, resolution=args.res)
    s = run_demo(cfg)
    print(f"[{s['variant']}] composition of {s['frames']} test frames against path-traced ground "
          f"truth ({cfg.resolution}px):")
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


# ----------------------------------------------------------------------------- reconstruct

def _add_reconstruct(sub) -> None:
    p = sub.add_parser("reconstruct", help="step 1: surfel radiance + geometry from images",
                       description="Fit surfels to a NeRF-synthetic, COLMAP or LLFF folder. Resumes "
                                   "from RUN_DIR/checkpoint.npz when present. Every scalar field "
                                   "of RadianceConfig is a flag (--lambda-d2n, --lr-means, ...).")
    p.add_argument("data", metavar="DATA_DIR")
    p.add_argument("--out", required=True, metavar="RUN_DIR")
    kind = p.add_mutually_exclusive_group()
    kind.add_argument("--object", dest="preset", action="store_const", const="object",
                      help="object preset (masks, visual-hull init, mask loss; default)")
    kind.add_argument("--scene", dest="preset", action="store_const", const="scene",
                      help="scene preset (dataset points or random init, no mask loss)")
    p.add_argument("--iterations", type=int, help="training iterations (default 3000)")
    p.add_argument("--resolution-scale", "-r", type=int, default=1, choices=(1, 2, 4, 8))
    p.add_argument("--white-background", action="store_true")
    p.add_argument("--init", help="auto | hull | points | nearfar | random | PATH.ply (nearfar: LLFF near/far frusta, plane-swept depths)")
    p.add_argument("--time-limit", type=float, dest="time_limit_s",
                   help="stop (and checkpoint) after this many seconds")
    p.add_argument("--densify", action="store_true",
                   help="2DGS clone/split + opacity resets (densify until half of the run, reset "
                        "at its quarter and half; default: prune only, measured better on both "
                        "presets within CPU budgets; useful after a random init)")
    p.add_argument("--variant", default="auto")
    p.add_argument("--quiet", action="store_true")
    add_config_arguments(p, RadianceConfig, exclude=("preset",), presets=RECON_PRESETS)
    p.set_defaults(func=_cmd_reconstruct, preset="object")


def _cmd_reconstruct(args) -> int:
    set_variant(args.variant)
    kw = config_overrides(args, RadianceConfig)
    kw.pop("densify", None)
    if args.densify:
        kw["densify"] = scaled_density_schedule(kw.get("iterations", RadianceConfig.iterations))
    cfg = RadianceConfig.from_preset(args.preset, **kw)      # flags checked before the data
    data = load_dataset(args.data, white_background=args.white_background,
                        resolution_scale=args.resolution_scale)
    write_run_info(args.out, args.data, args.preset, args.resolution_scale, args.white_background)
    s = train_radiance(data, args.out, cfg, progress=not args.quiet)
    print(f"step 1 done: {s['iterations']} iterations in {s['train_seconds']:.0f} s, {s['surfels']} surfels, "
          f"test PSNR {s['psnr_test']:.2f} dB -> {args.out}/point_cloud.ply")
    return 0


def _add_render(sub) -> None:
    p = sub.add_parser("render", help="render a reconstruction run and write metrics")
    p.add_argument("run", metavar="RUN_DIR")
    p.add_argument("--views", choices=("test", "train"), default="test")
    p.add_argument("--variant", default="auto")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_render)


def _cmd_render(args) -> int:
    set_variant(args.variant)
    r = render_run(args.run, args.views, progress=not args.quiet)
    extra = "".join(f", {k} {r[k]:.3f}" for k in ("normal_mae_deg", "depth_rel") if k in r)
    print(f"{args.views}: PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.4f}{extra} over {r['views']} views "
          f"-> {args.run}/metrics_{args.views}.json")
    return 0


def _add_export_mesh(sub) -> None:
    p = sub.add_parser("export-mesh", help="a triangle mesh of a reconstruction (TSDF or Poisson)",
                       description="TSDF fusion of depth rendered from the training cameras "
                                   "(2DGS's extraction, with space carving) or screened Poisson "
                                   "on the surfel centres and normals (pymeshlab). Vertex colours "
                                   "from the radiance, or the albedo after step 2. Writes the mesh "
                                   "(.ply/.obj/.glb) and MESH.json.")
    p.add_argument("run", metavar="RUN_DIR")
    p.add_argument("--out", required=True, metavar="MESH.ply")
    p.add_argument("--method", choices=MESH_METHODS, default=None)
    p.add_argument("--preset", choices=tuple(MESH_PRESETS), default="default")
    p.add_argument("--resolution", type=int, default=None, metavar="N",
                   help="TSDF voxels along the longest side; Poisson octree depth log2(N)")
    add_config_arguments(p, MeshConfig, presets=MESH_PRESETS)
    p.add_argument("--variant", default="auto")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_export_mesh)


def _cmd_export_mesh(args) -> int:
    set_variant(args.variant)
    cfg = MeshConfig(**{**MESH_PRESETS[args.preset], **config_overrides(args, MeshConfig)})
    s = export_mesh(args.run, args.out, cfg, progress=not args.quiet)
    print(f"{s['mesh']}: {s['vertices']} vertices, {s['faces']} faces ({s['method']}, colour "
          f"{s['colour']}, watertight {s['watertight']}) in {s['seconds']} s")
    return 0


# ----------------------------------------------------------------------------- decompose / relight

def _add_decompose(sub) -> None:
    p = sub.add_parser("decompose", help="step 2: materials + env map + SOPs from a step-1 run",
                       description="Place and bake Surface Octahedral Probes, then optimise "
                                   "albedo/roughness/metallic, an octahedral env map and the "
                                   "probe textures with deferred PBR. Writes RUN_DIR/material "
                                   "(or --out); resumes from its checkpoint.npz. Every scalar "
                                   "field of MaterialConfig is a flag (--lr-env, --probe-res, ...).")
    p.add_argument("run", metavar="RUN_DIR")
    p.add_argument("--out", metavar="DIR", help="output folder (default RUN_DIR/material)")
    p.add_argument("--visibility", choices=KINDS,
                   help="occlusion/indirect source (default sops; trace = per-iteration "
                        "ray tracing baseline)")
    p.add_argument("--rays", type=int, help=f"S_r (default {MaterialConfig.rays})")
    p.add_argument("--probes", type=int, dest="probe_count",
                   help=f"number of SOPs (default {MaterialConfig.probe_count})")
    p.add_argument("--no-indirect", dest="indirect", action="store_const", const=False,
                   help="leave out the indirect term")
    p.add_argument("--time-limit", type=float, dest="time_limit_s",
                   help="stop (and save) after this many seconds")
    p.add_argument("--variant", default="auto")
    p.add_argument("--quiet", action="store_true")
    add_config_arguments(p, MaterialConfig)
    p.set_defaults(func=_cmd_decompose)


def _cmd_decompose(args) -> int:
    set_variant(args.variant)
    cfg = MaterialConfig(**config_overrides(args, MaterialConfig))
    s = train_material(args.run, args.out, cfg, progress=not args.quiet)
    sp = s["median_step_split_s"]
    print(f"step 2 ({cfg.visibility}) done: {s['iterations']} iterations in "
          f"{s['train_seconds']:.0f} s ({sum(sp.values()):.3f} s/it median), test PBR PSNR "
          f"{s['psnr_test']:.2f} dB -> {args.out or args.run + '/material'}")
    return 0


def _add_relight(sub) -> None:
    p = sub.add_parser("relight", help="render a step-2 run under a new environment map",
                       description="Deferred PBR of the relightable surfels under ENVMAP "
                                   "(equirect .hdr/.exr, Z-up, or our octahedral EXR); "
                                   "writes PNGs and metrics.json (relighting PSNR/SSIM, "
                                   "albedo PSNR, when the dataset has the ground truth).")
    p.add_argument("run", metavar="RUN_DIR")
    p.add_argument("--envmap", required=True, metavar="MAP")
    p.add_argument("--material-dir", metavar="DIR", help="step-2 folder (default RUN_DIR/material)")
    p.add_argument("--material", metavar="EDIT",
                   help="edit the object's material before relighting: comma-separated "
                        "albedo=R,G,B (linear) or scale=S[,S,S], roughness=X, metallic=Y, "
                        "e.g. albedo=0.8,0.1,0.1,roughness=0.2")
    p.add_argument("--material-mask", metavar="MASK",
                   help="surfels the edit applies to: box:x0,y0,z0,x1,y1,z1 (world space) or a "
                        "file of surfel indices (.npy or text); default the whole object")
    p.add_argument("--views", choices=("test", "train"), default="test")
    p.add_argument("--rays", type=int, default=256, help="S_r per shading point (default 256)")
    p.add_argument("--sampling", choices=SAMPLINGS, default="mis",
                   help="estimator: mis = env-map + BRDF importance sampling (default), "
                        "uniform = the paper's training estimator")
    p.add_argument("--envmap-res", type=int, help="octahedral resolution of the map (default: "
                   "an equirect map's height, at most 1024)")
    p.add_argument("--max-views", type=int)
    p.add_argument("--scale", type=float, default=1.0, help="env map radiance scale")
    p.add_argument("--out", metavar="DIR")
    p.add_argument("--variant", default="auto")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_relight)


def _cmd_relight(args) -> int:
    set_variant(args.variant)
    edit = parse_material_spec(args.material) if args.material else None
    mask = None
    if args.material_mask:
        if edit is None:
            raise SystemExit("comgs relight: --material-mask needs --material")
        from comgs_dr.surfels import load_ply
        mdir = Path(args.material_dir) if args.material_dir else Path(args.run) / "material"
        mask = parse_mask_spec(args.material_mask, load_ply(str(mdir / "point_cloud.ply")).count)
    r = relight_run(args.run, args.envmap, args.material_dir, args.views, args.rays,
                    envmap_scale=args.scale, out_dir=args.out, progress=not args.quiet,
                    max_views=args.max_views, sampling=args.sampling, edit=edit,
                    edit_mask=mask, envmap_res=args.envmap_res)
    extra = "".join(f", {k} {r[k]:.3f}" for k in ("relight_psnr", "relight_psnr_aligned",
                                                   "relight_ssim", "albedo_psnr")
                    if k in r)
    print(f"relit {r['views']} {args.views} views under {args.envmap} "
          f"(visibility {r['visibility']}, indirect {r['indirect']}){extra}")
    return 0


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
    p.add_argument("--label", choices=("unknown", "indoor", "outdoor"), default=d.label)
    p.add_argument("--width", type=int, default=d.width, help=f"trace width (default {d.width})")
    p.add_argument("--height", type=int, default=d.height,
                   help=f"trace height (default {d.height})")
    p.add_argument("--exclude-radius", type=float, default=d.exclude_radius,
                   help="leave out surfels this close to the position (the object itself)")
    p.add_argument("--max-hits", type=int, default=d.max_hits)
    p.add_argument("--supersample", type=int, default=d.supersample)
    p.add_argument("--oct-res", type=int, default=d.oct_res,
                   help=f"octahedral map side (default {d.oct_res})")
    p.add_argument("--backend", choices=("net", "mean", "push_pull", "sh", "diffusers"),
                   default="net", help="completion backend (default net: the shipped weights)")
    p.add_argument("--weights", metavar="PATH", help="completion-net checkpoint (backend net)")
    p.add_argument("--net-resolution", type=int, nargs=2, metavar=("H", "W"),
                   help="network input size (default: the size the weights were trained at)")
    p.add_argument("--diffusers-dir", metavar="DIR",
                   help="local diffusers inpainting model (backend diffusers); prompt "
                        "embeddings come from its text encoder or DIR/ev_embeddings.pt "
                        "({'xi_b': [L, D], 'xi_d': [L, D]})")
    p.add_argument("--steps", type=int, default=30, help="diffusion steps (backend diffusers)")
    p.add_argument("--variant", default="auto")
    add_config_arguments(p, EstimateConfig)
    p.set_defaults(func=_cmd_estimate_light)


def _estimate_backend(args):
    if args.backend == "net":
        res = tuple(args.net_resolution) if args.net_resolution else None
        return backends.load_network_backend(args.weights, res)
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
    r = estimate_light(args.scene, args.at, cfg, _estimate_backend(args))
    paths = write_outputs(r, args.out)
    print(f"coverage {100 * r['coverage']:.1f}%, backend {r['meta']['backend']}, "
          f"{len(r['lights'])} light(s), peak radiance {float(r['hdr'].max()):.3g}")
    print(f"{'step':<12}{'seconds':>10}")
    for k, v in r["timings"].items():
        print(f"{k:<12}{v:>10.3f}")
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


# ----------------------------------------------------------------------------- train-completion

def _add_train_completion(sub) -> None:
    p = sub.add_parser("train-completion", help="train the panorama completion network",
                       description="Generate the training set (Poly Haven maps minus the "
                                   "held-out ones, sunsky skies, path-traced rooms, traced "
                                   "surfel masks) and train the EV-conditioned completion "
                                   "network in two steps within --minutes.")
    train_completion.add_arguments(p)
    p.set_defaults(func=_cmd_train_completion)


def _cmd_train_completion(args) -> int:
    set_variant("llvm_ad_rgb")
    return train_completion.run_from_args(args)


def _add_train_light_head(sub) -> None:
    p = sub.add_parser("train-light-head", help="train the light head (power of clipped lights)",
                       description="Generate clipped-light regions from the real maps minus "
                                   "the held-out ones, sunsky skies and path-traced rooms at "
                                   "several sizes, and fit the light head (minutes).")
    train_light_head.add_arguments(p)
    p.set_defaults(func=_cmd_train_light_head)


def _cmd_train_light_head(args) -> int:
    set_variant("llvm_ad_rgb")
    return train_light_head.run_from_args(args)


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
                   help="default: 10k shadow probes per object (paper); fast: 2k")
    p.add_argument("--shadow-probes", type=int, metavar="N", help="shadow probes per object")
    p.add_argument("--label", choices=("unknown", "indoor", "outdoor"), default="unknown",
                   help="scene label for the lighting estimation")
    p.add_argument("--variant", default="auto")
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
        cfg = dataclasses.replace(cfg, shadow=dataclasses.replace(cfg.shadow,
                                                                  count=args.shadow_probes))
    estimator = None
    if args.env is None:
        scene_ply = str(Path(args.scene_run) / "point_cloud.ply")
        ecfg = EstimateConfig(label=args.label)
        backend = backends.load_network_backend()
        estimator = lambda pos: estimate_light(scene_ply, pos, ecfg, backend)["hdr"]  # noqa: E731
    s = compose(args.scene_run, objects, args.placement, args.out, env=args.env,
                estimator=estimator, cfg=cfg, progress=not args.quiet)
    t = s["timings"]
    print(f"{'part':<20}{'seconds':>10}")
    for k in ("lighting", "probe_placement", "occlusion_tracing", "total"):
        print(f"{k:<20}{t[k]:>10.2f}")
    pr = s["pairs"]
    print(f"{s['probes']['shadow']} shadow probes; occlusion pairs traced {len(pr['traced'])}, "
          f"reused {len(pr['reused'])}, culled {len(pr['culled'])}; wrote {args.out}")
    return 0


def _add_render_comp(sub) -> None:
    p = sub.add_parser(
        "render-comp", help="render a composition along NeRF-synthetic cameras",
        description="Render COMP_DIR (from `comgs compose`) along the cameras of a "
                    "NeRF-synthetic transforms.json into COMP_DIR/renders/<variant>/ and, with "
                    "--gt-dir, score against GT_DIR/<basename>.png into "
                    "COMP_DIR/metrics_<variant>.json (psnr, ssim, frame_seconds, per frame).")
    p.add_argument("comp_dir", metavar="COMP_DIR")
    p.add_argument("--cameras", required=True, metavar="transforms.json")
    p.add_argument("--variant", choices=RENDER_VARIANTS, default="sop",
                   help="sop (cached shadows), trace (traced per frame), noshadow, paste")
    p.add_argument("--gt-dir", metavar="DIR", help="ground-truth PNGs named like the frames")
    p.add_argument("--material", action="append", default=[],
                   metavar="NAME:albedo=R,G,B,roughness=X,metallic=Y",
                   help="override an object's material (repeatable)")
    p.add_argument("--res", type=int, nargs="+", metavar="W [H]",
                   help="image size (default: the ground truth's, else the camera file's w/h)")
    p.add_argument("--rays", type=int, metavar="N", help="S_r (default 256)")
    p.add_argument("--variant-mitsuba", dest="mi_variant", default="auto", metavar="V")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_render_comp)


def _cmd_render_comp(args) -> int:
    set_variant(args.mi_variant)
    mats = {}
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
    line = f"{s['frames']} frames ({s['variant']}), {s['frame_seconds']:.3f} s/frame"
    if "psnr" in s:
        line += f", PSNR {s['psnr']:.2f} dB, SSIM {s['ssim']:.4f}"
    print(line + f"; renders in {s['renders']}")
    return 0


# ----------------------------------------------------------------------------- entry point

_SUBCOMMANDS = (_add_make_dataset, _add_demo, _add_report, _add_reconstruct, _add_render, _add_export_mesh, _add_decompose,
                _add_relight, _add_estimate_light, _add_train_completion, _add_train_light_head,
                _add_compose,
                _add_render_comp)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="comgs", description="ComGS object-scene composition on Dr.Jit / Mitsuba 3")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in _SUBCOMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``comgs``; returns the exit code (2 for usage and input errors)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2)
        return int(e.code or 0)
    problem = numeric_problem(parser, args)       # nan/inf/1e309, integers beyond 32 bits
    if problem:
        print(f"comgs {args.command}: error: {problem}", file=sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except TrainingInterrupted as e:     # SIGINT/SIGTERM: the checkpoint is written
        print(f"comgs {args.command}: stopped by {e}", file=sys.stderr)
        return e.exit_code
    except (FileNotFoundError, ValueError, ImportError) as e:
        print(f"comgs {args.command}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:                 # full disk, unwritable folder
        print(f"comgs {args.command}: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
