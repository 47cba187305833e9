"""The command line: ``comgs reconstruct``, ``render``, ``export-mesh``, ``decompose``, ``relight``.

Each command takes its flags from its config dataclass (``cli._flags.add_config_flags``);
the tables below only say where a flag is spelled differently from its field.
"""
from __future__ import annotations

from comgs_dr import set_variant
from comgs_dr.cli._flags import Spelling, add_config_flags, field_overrides
from comgs_dr.cli.sfm import add_sfm_flags, sfm_flags_config, sfm_if_photos
from comgs_dr.core.config import shared_options
from comgs_dr.data.load import load_dataset
from comgs_dr.shading.shade import SAMPLINGS
from comgs_dr.shading.visibility import KINDS
from comgs_dr.stages.decompose import MaterialConfig, train_material
from comgs_dr.stages.export_mesh import METHODS as MESH_METHODS
from comgs_dr.stages.export_mesh import PRESETS as MESH_PRESETS
from comgs_dr.stages.export_mesh import MeshConfig, export_mesh
from comgs_dr.stages.reconstruct import (
    PRESETS as RECON_PRESETS,
    RadianceConfig,
    scaled_density_schedule,
    train_radiance,
)
from comgs_dr.stages.relight import VIEWS, RelightConfig, relight_run
from comgs_dr.stages.render_run import RenderConfig, render_run
from comgs_dr.train.run import write_run_info

# ----------------------------------------------------------------------------- reconstruct

RECONSTRUCT_FLAGS = {
    "iterations": Spelling(help="training iterations"),
    "init": Spelling(help="auto | hull | points | nearfar | random | PATH.ply (nearfar: LLFF "
                     "near/far frusta, plane-swept depths)"),
    "time_limit_s": Spelling(("--time-limit",), help="stop (and checkpoint) after this many "
                             "seconds"),
    "restore_best": Spelling(("--no-restore",), const=False, help="end on the final state "
                             "even when it fell > 0.5 dB below the best evaluated one (the "
                             "fall is still reported as 'diverged'); same as --restore-best "
                             "false"),
}


def _add_reconstruct(sub) -> None:
    p = sub.add_parser(
        "reconstruct", parents=[shared_options(out=dict(required=True, metavar="RUN_DIR"))],
        help="step 1: surfel radiance + geometry from images",
        description="Fit surfels to a NeRF-synthetic, COLMAP or LLFF folder, or to a folder "
                    "of photos or a video: `comgs sfm` then runs first into RUN_DIR/sfm "
                    "(or --sfm-out; reused when complete) and the scene preset is the "
                    "default. Resumes from RUN_DIR/checkpoint.npz when present. Every scalar "
                    "field of RadianceConfig is a flag (--lambda-d2n, --lr-means, ...), and "
                    "every one of SfmConfig (--max-size, --matching, ...).")
    p.add_argument("data", metavar="DATA_DIR",
                   help="a dataset (NeRF transforms, COLMAP, LLFF), a folder of photos or a "
                        "video file")
    # preset picks the RadianceConfig.from_preset base the field flags then override
    kind = p.add_mutually_exclusive_group()
    kind.add_argument("--object", dest="preset", action="store_const", const="object",
                      help="object preset (masks, visual-hull init, mask loss; default for "
                           "a dataset)")
    kind.add_argument("--scene", dest="preset", action="store_const", const="scene",
                      help="scene preset (dataset points or random init, no mask loss; "
                           "default for photos or a video)")
    # not RadianceConfig fields: how the dataset is loaded (load_dataset)
    p.add_argument("--resolution-scale", "-r", type=int, default=1, choices=(1, 2, 4, 8))
    p.add_argument("--white-background", action="store_true")
    # RadianceConfig.densify is a schedule (a dict), not a scalar: the switch picks the
    # schedule scaled to the run's iterations
    p.add_argument("--densify", action="store_true", dest="densify_scaled",
                   help="2DGS clone/split + opacity resets (densify until half of the run, reset "
                        "at its quarter and half; default: prune only, since a dense init needs "
                        "no new surfels; useful after a random init)")
    add_config_flags(p, RadianceConfig, RECONSTRUCT_FLAGS, exclude=("preset", "densify"),
                     presets=RECON_PRESETS)
    add_sfm_flags(p)
    # preset None: object for a dataset, scene for photos (_cmd_reconstruct)
    p.set_defaults(func=_cmd_reconstruct, preset=None)


def _cmd_reconstruct(args) -> int:
    set_variant(args.mitsuba_variant)
    kw = field_overrides(args, RadianceConfig)
    if args.densify_scaled:
        kw["densify"] = scaled_density_schedule(kw.get("iterations", RadianceConfig.iterations))
    RadianceConfig.from_preset(args.preset or "object", **kw)  # flags checked before any work
    sfm_flags_config(args)
    data_dir, sfm = sfm_if_photos(args.data, args.out, args, progress=not args.quiet)
    preset = args.preset or ("scene" if sfm else "object")
    if sfm and not args.preset:
        print("photos and video frames have no masks: the scene preset (--object to override)")
    cfg = RadianceConfig.from_preset(preset, **kw)
    data = load_dataset(data_dir, white_background=args.white_background,
                        resolution_scale=args.resolution_scale)
    write_run_info(args.out, data_dir, preset, args.resolution_scale, args.white_background)
    s = train_radiance(data, args.out, cfg, progress=not args.quiet)
    print(f"step 1 done: {s['iterations']} iterations in {s['train_seconds']:.0f} s, {s['surfels']} surfels, "
          f"test PSNR {s['psnr_test']:.2f} dB, background {s['background']} -> "
          f"{args.out}/point_cloud.ply")
    d = s.get("diverged")
    if d:
        kept = (f"the state of iteration {d['best_iteration']} was restored" if d["restored"]
                else "the final state was kept (--no-restore)")
        print(f"  diverged: training-view PSNR {d['best_psnr_select']} dB at iteration "
              f"{d['best_iteration']} fell to {d['final_psnr_select']} dB; {kept}")
    return 0


# ----------------------------------------------------------------------------- render, export-mesh

def _add_render(sub) -> None:
    p = sub.add_parser("render", parents=[shared_options()],
                       help="render a reconstruction run and write metrics")
    p.add_argument("run", metavar="RUN_DIR")
    add_config_flags(p, RenderConfig, {"views": Spelling(choices=VIEWS)})
    p.set_defaults(func=_cmd_render)


def _cmd_render(args) -> int:
    cfg = RenderConfig(**field_overrides(args, RenderConfig))
    set_variant(args.mitsuba_variant)
    r = render_run(args.run, cfg.views, progress=not args.quiet, max_hits=cfg.max_hits)
    extra = "".join(f", {k} {r[k]:.3f}" for k in ("normal_mae_deg", "depth_rel") if k in r)
    print(f"{cfg.views}: PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.4f}{extra} over {r['views']} views "
          f"-> {args.run}/metrics_{cfg.views}.json")
    return 0


def _add_export_mesh(sub) -> None:
    p = sub.add_parser(
        "export-mesh", parents=[shared_options(out=dict(required=True, metavar="MESH.ply"))],
        help="a triangle mesh of a reconstruction (TSDF or Poisson)",
        description="TSDF fusion of depth rendered from the training cameras "
                    "(2DGS's extraction, with space carving) or screened Poisson "
                    "on the surfel centres and normals (pymeshlab). Vertex colours "
                    "from the radiance, or the albedo after step 2. Writes the mesh "
                    "(.ply/.obj/.glb) and MESH.json.")
    p.add_argument("run", metavar="RUN_DIR")
    # not a MeshConfig field: the preset is the config the flags then override
    p.add_argument("--preset", choices=tuple(MESH_PRESETS), default="default")
    add_config_flags(p, MeshConfig, {
        "method": Spelling(choices=MESH_METHODS),
        "resolution": Spelling(metavar="N", help="TSDF voxels along the longest side; "
                               "Poisson octree depth log2(N)")}, presets=MESH_PRESETS)
    p.set_defaults(func=_cmd_export_mesh)


def _cmd_export_mesh(args) -> int:
    set_variant(args.mitsuba_variant)
    cfg = MeshConfig(**{**MESH_PRESETS[args.preset], **field_overrides(args, MeshConfig)})
    s = export_mesh(args.run, args.out, cfg, progress=not args.quiet)
    print(f"{s['mesh']}: {s['vertices']} vertices, {s['faces']} faces ({s['method']}, colour "
          f"{s['colour']}, watertight {s['watertight']}) in {s['seconds']} s")
    return 0


# ----------------------------------------------------------------------------- decompose, relight

DECOMPOSE_FLAGS = {
    "visibility": Spelling(choices=KINDS, help="occlusion/indirect source (trace: "
                           "per-iteration ray tracing, the baseline)"),
    "rays": Spelling(help="S_r, light samples per shading point"),
    "probe_count": Spelling(("--probes",), help="number of SOPs"),
    "indirect": Spelling(("--no-indirect",), const=False, help="leave out the indirect term"),
    "time_limit_s": Spelling(("--time-limit",), help="stop (and save) after this many seconds"),
}


def _add_decompose(sub) -> None:
    p = sub.add_parser(
        "decompose", parents=[shared_options(out=dict(metavar="DIR", help=(
            "output folder (default RUN_DIR/material)")))],
        help="step 2: materials + env map + SOPs from a step-1 run",
        description="Place and bake Surface Octahedral Probes, then optimise "
                    "albedo/roughness/metallic, an octahedral env map and the "
                    "probe textures with deferred PBR. Writes RUN_DIR/material "
                    "(or --out); resumes from its checkpoint.npz. Every scalar "
                    "field of MaterialConfig is a flag (--lr-env, --probe-res, ...).")
    p.add_argument("run", metavar="RUN_DIR")
    add_config_flags(p, MaterialConfig, DECOMPOSE_FLAGS)
    p.set_defaults(func=_cmd_decompose)


def _cmd_decompose(args) -> int:
    set_variant(args.mitsuba_variant)
    cfg = MaterialConfig(**field_overrides(args, MaterialConfig))
    s = train_material(args.run, args.out, cfg, progress=not args.quiet)
    sp = s["median_step_split_s"]
    print(f"step 2 ({cfg.visibility}) done: {s['iterations']} iterations in "
          f"{s['train_seconds']:.0f} s ({sum(sp.values()):.3f} s/it median), test PBR PSNR "
          f"{s['psnr_test']:.2f} dB -> {args.out or args.run + '/material'}")
    return 0


RELIGHT_FLAGS = {
    "views": Spelling(choices=VIEWS),
    "rays": Spelling(help="S_r per shading point"),
    "sampling": Spelling(choices=SAMPLINGS, help="estimator: mis = env-map + BRDF importance "
                         "sampling, uniform = the paper's training estimator"),
    "visibility": Spelling(choices=KINDS, help="occlusion source (None: the step-2 run's)"),
    "envmap_res": Spelling(help="octahedral resolution of the map (None: an equirect map's "
                           "height, at most 1024)"),
    "envmap_scale": Spelling(("--scale",), help="env map radiance scale"),
    "material": Spelling(metavar="EDIT", help="edit the object's material before relighting: "
                         "comma-separated albedo=R,G,B (linear) or scale=S[,S,S], roughness=X, "
                         "metallic=Y, e.g. albedo=0.8,0.1,0.1,roughness=0.2"),
    "material_mask": Spelling(metavar="MASK", help="surfels the edit applies to: "
                              "box:x0,y0,z0,x1,y1,z1 (world space) or a file of surfel "
                              "indices (.npy or text); None: the whole object"),
}


def _add_relight(sub) -> None:
    p = sub.add_parser(
        "relight", parents=[shared_options(out=dict(metavar="DIR", help=(
            "output folder (default MATERIAL_DIR/relight_<map>_<views>)")))],
        help="render a step-2 run under a new environment map",
        description="Deferred PBR of the relightable surfels under ENVMAP "
                    "(equirect .hdr/.exr, Z-up, or our octahedral EXR); "
                    "writes PNGs and metrics.json (relighting PSNR/SSIM, "
                    "albedo PSNR, when the dataset has the ground truth).")
    p.add_argument("run", metavar="RUN_DIR")
    # not RelightConfig fields: the inputs of relight_run (the map, the step-2 folder)
    p.add_argument("--envmap", required=True, metavar="MAP")
    p.add_argument("--material-dir", metavar="DIR", help="step-2 folder (default RUN_DIR/material)")
    add_config_flags(p, RelightConfig, RELIGHT_FLAGS)
    p.set_defaults(func=_cmd_relight)


def _cmd_relight(args) -> int:
    cfg = RelightConfig(**field_overrides(args, RelightConfig))
    set_variant(args.mitsuba_variant)
    r = relight_run(args.run, args.envmap, args.material_dir, cfg=cfg, out_dir=args.out,
                    progress=not args.quiet)
    extra = "".join(f", {k} {r[k]:.3f}" for k in ("relight_psnr", "relight_psnr_aligned",
                                                   "relight_ssim", "albedo_psnr")
                    if k in r)
    print(f"relit {r['views']} {cfg.views} views under {args.envmap} "
          f"(visibility {r['visibility']}, indirect {r['indirect']}){extra}")
    return 0
