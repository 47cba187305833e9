"""The command line: ``comgs cut RUN --out OBJECT_RUN [--data DATASET] [--object-box ...]
[--masks]`` (``stages.cut_object``). Register with ``_add_cut(subparsers)``."""
from __future__ import annotations

import sys

from comgs_dr import set_variant
from comgs_dr.core.config import add_config_arguments, config_overrides, shared_options
from comgs_dr.stages.cut_object import BOX_FRAMES, PLANE_POINTS, CutConfig, cut_object, summary_text


#: Help of the config fields (× s: a fraction of the scene size, the cameras' median distance
#: to their look-at point); the rest get ``core.config.add_config_arguments``'s default help.
FIELD_HELP = {
    "plane_tolerance": "RANSAC inlier distance (× s)",
    "plane_radius": "only points this close to the look-at point vote for the plane (× s)",
    "plane_max_tilt_deg": "largest angle between the plane normal and the cameras' mean up",
    "plane_min_inliers": "least share of the voting points on the plane",
    "min_opacity": "fainter surfels neither vote nor link the object",
    "min_height": "kept surfels are at least this high above the plane (× s)",
    "slab_height": "surfels lower than this are kept only under the object's footprint (× s)",
    "grow_radius": "surfels closer than this are linked (× s)",
    "grow_spacing": "...or closer than this many times their own spacing (median 4th-nearest "
                    "neighbour distance near the look-at point); 0: --grow-radius only",
    "footprint": "horizontal reach of the object's footprint for its base (× s)",
    "seed_distance": "the object must come this close to the look-at point (× s)",
    "min_component": "linked groups of fewer surfels are floaters",
}


def _add_cut(sub) -> None:
    p = sub.add_parser(
        "cut", parents=[shared_options(out=dict(required=True, metavar="OBJECT_RUN"))],
        help="cut the object out of a whole-capture step-1 run (no masks needed)",
        description="Fit the support plane under the cameras' look-at point (RANSAC on the "
                    "surfels or the SfM points), keep what stands on it near that point (or "
                    "inside --object-box), and write an object run: point_cloud.ply in the "
                    "object frame (plane z = 0, up +z), cut.json (the transform, the plane, "
                    "the share of kept surfels below the plane and in a thin slab above it), "
                    "the cameras in that frame; --masks adds alpha masks and an RGBA object "
                    "dataset for an object-only step 1. Lengths are fractions of the scene "
                    "size (the cameras' median distance to their look-at point).")
    p.add_argument("run", metavar="RUN_DIR", help="a `comgs reconstruct` run of the whole capture")
    p.add_argument("--data", metavar="DATASET", default=None,
                   help="the capture's dataset (default: the run's, from its run.json)")
    p.add_argument("--object-box", dest="object_box", nargs=6, type=float, default=None,
                   metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="keep the surfels inside this box instead of growing the object from "
                        "the look-at point (frame: --box-frame)")
    p.add_argument("--masks", dest="masks", action="store_const", const=True, default=None,
                   help="also write masks/<image>.png (the kept surfels' coverage per photo; "
                        "the dataset's own masks/ used as they are) and data/images/ (RGBA "
                        "photos) for `comgs reconstruct OBJECT_RUN/data`")
    p.add_argument("--plane-points", dest="plane_points", choices=PLANE_POINTS, default=None,
                   help="fit the plane to the opaque surfels' centres or the SfM points "
                        f"(default {CutConfig.plane_points!r})")
    p.add_argument("--box-frame", dest="box_frame", choices=BOX_FRAMES, default=None,
                   help="frame of --object-box: world (the run's point_cloud.ply) or plane "
                        f"(z up from the plane; default {CutConfig.box_frame!r})")
    for name, text in FIELD_HELP.items():
        tp = type(getattr(CutConfig, name))
        p.add_argument("--" + name.replace("_", "-"), dest=name, type=tp, default=None,
                       metavar=tp.__name__.upper(),
                       help=f"{text} (default {getattr(CutConfig, name)!r})")
    add_config_arguments(p, CutConfig)
    p.set_defaults(func=_cmd_cut)


def _cmd_cut(args) -> int:
    """Exit 0, or 2 with ``comgs cut: error: FILE: problem`` on stderr."""
    try:
        cfg = CutConfig(**config_overrides(args, CutConfig))
        set_variant(args.mitsuba_variant)
        s = cut_object(args.run, args.out, cfg, data_dir=args.data, progress=not args.quiet)
    except (FileNotFoundError, ValueError) as e:      # CutError, DatasetError, bad flags
        print(f"comgs cut: error: {e}", file=sys.stderr)
        return 2
    print(summary_text(s))
    return 0
