"""The command line: ``comgs reconstruct``, ``render``, ``export-mesh``, ``decompose``, ``relight``."""
from __future__ import annotations

from pathlib import Path

from comgs_dr import set_variant
from comgs_dr.core.config import add_config_arguments, config_overrides
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
from comgs_dr.stages.relight import relight_run
from comgs_dr.stages.render_run import render_run
from comgs_dr.surfels.edit import parse_mask_spec, parse_material_spec
from comgs_dr.train.run import write_run_info

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
                        "at its quarter and half; default: prune only: on the 48-view teapot "
                        "clone/split gave -0.3 dB at 1250 its with 50%% more surfels, see "
                        "docs/step1.md; useful after a random init)")
    p.add_argument("--no-restore", action="store_true",
                   help="end on the final state even when it fell > 0.5 dB below the best "
                        "evaluated one (the fall is still reported as 'diverged'); same as "
                        "--restore-best false")
    p.add_argument("--variant", default="auto", metavar="MITSUBA_VARIANT",
                   help="Mitsuba variant: auto (default), llvm_ad_rgb (CPU) or cuda_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    add_config_arguments(p, RadianceConfig, exclude=("preset",), presets=RECON_PRESETS)
    p.set_defaults(func=_cmd_reconstruct, preset="object")


def _cmd_reconstruct(args) -> int:
    set_variant(args.variant)
    kw = config_overrides(args, RadianceConfig)
    kw.pop("densify", None)
    if args.no_restore:
        kw["restore_best"] = False
    if args.densify:
        kw["densify"] = scaled_density_schedule(kw.get("iterations", RadianceConfig.iterations))
    cfg = RadianceConfig.from_preset(args.preset, **kw)      # flags checked before the data
    data = load_dataset(args.data, white_background=args.white_background,
                        resolution_scale=args.resolution_scale)
    write_run_info(args.out, args.data, args.preset, args.resolution_scale, args.white_background)
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


def _add_render(sub) -> None:
    p = sub.add_parser("render", help="render a reconstruction run and write metrics")
    p.add_argument("run", metavar="RUN_DIR")
    p.add_argument("--views", choices=("test", "train"), default="test")
    p.add_argument("--variant", default="auto", metavar="MITSUBA_VARIANT",
                   help="Mitsuba variant: auto (default), llvm_ad_rgb (CPU) or cuda_ad_rgb")
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
    p.add_argument("--variant", default="auto", metavar="MITSUBA_VARIANT",
                   help="Mitsuba variant: auto (default), llvm_ad_rgb (CPU) or cuda_ad_rgb")
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
    p.add_argument("--variant", default="auto", metavar="MITSUBA_VARIANT",
                   help="Mitsuba variant: auto (default), llvm_ad_rgb (CPU) or cuda_ad_rgb")
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
    p.add_argument("--variant", default="auto", metavar="MITSUBA_VARIANT",
                   help="Mitsuba variant: auto (default), llvm_ad_rgb (CPU) or cuda_ad_rgb")
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
