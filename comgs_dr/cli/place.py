"""The command line: ``comgs place SCENE_RUN --object NAME=RUN (--view VIEW --pixel X Y |
--at X Y Z) [--scale S] [--yaw DEG] [--upright] --out transform.json``
(``stages.place``). Register with ``_add_place(subparsers)``."""
from __future__ import annotations

from comgs_dr import set_variant
from comgs_dr.cli._flags import Spelling, add_config_flags, field_overrides
from comgs_dr.core.config import shared_options
from comgs_dr.stages.place import PlaceConfig, place

SPELLINGS = {
    "scale": Spelling(help="the object's uniform scale in the scene"),
    "yaw_deg": Spelling(("--yaw",), metavar="DEG",
                        help="turn about the object's own up axis (degrees)"),
    "upright": Spelling(("--upright",), const=True,
                        help="stand the object along world up (+Z), not the surface normal; "
                             "refused on surfaces steeper than --max-tilt-deg"),
    "max_tilt_deg": Spelling(help="with --upright: the steepest surface accepted (degrees)"),
    "min_weight": Spelling(help="the pixel's ray hits where its accumulated opacity reaches "
                                "this"),
    "normal_radius": Spelling(help="scene surfels this close fit the surface plane (× the "
                                   "placed object's size)"),
    "floater_share": Spelling(help="share of the object's surfels allowed below its base and "
                                   "under the surface (floaters)"),
    "clearance": Spelling(help="gap between the object's lowest surfels and the surface (× "
                               "its size)"),
}


def _add_place(sub) -> None:
    p = sub.add_parser(
        "place", parents=[shared_options(out=dict(required=True, metavar="TRANSFORM_JSON",
                                                  help="placement file to write, or to add "
                                                       "the object to (compose --placement)"))],
        help="stand an object on the scene's surface at a pixel of a photo -> transform.json",
        description="Cast the ray of pixel X Y of the scene photo VIEW into the scene run's "
                    "surfels (or take --at X Y Z, the point_cloud.ply frame), stand the "
                    "object's base (the centre of its footprint at its lowest surfels; the "
                    "object's own frame is Z-up) on the hit point along the surface normal "
                    "(a plane fitted to the surfels around it) or along world up "
                    "(--upright), lift it until its surfels clear the surface, and write or "
                    "add its entry {NAME: {\"transform\": 16 floats}} to TRANSFORM_JSON, in "
                    "the scene dataset's frame (what `comgs compose --placement` reads). "
                    "Pixel (X, Y): column X, row Y from the top-left corner of the image file.")
    p.add_argument("scene_run", metavar="SCENE_RUN", help="a `comgs reconstruct` run of the scene")
    p.add_argument("--object", dest="object", required=True, metavar="NAME=RUN",
                   help="the object's name in transform.json and its run folder "
                        "(RUN/material/point_cloud.ply or RUN/point_cloud.ply) or .ply file")
    p.add_argument("--view", dest="view", default=None, metavar="VIEW",
                   help="the scene photo: its image name (with or without extension) or its "
                        "index among the capture's views (train, then test)")
    p.add_argument("--pixel", dest="pixel", nargs=2, type=float, default=None,
                   metavar=("X", "Y"), help="the pixel of VIEW the object stands on")
    p.add_argument("--at", dest="at", nargs=3, type=float, default=None,
                   metavar=("X", "Y", "Z"),
                   help="stand the object on this point instead (the scene run's "
                        "point_cloud.ply frame)")
    add_config_flags(p, PlaceConfig, SPELLINGS)
    p.set_defaults(func=_cmd_place)


def _cmd_place(args) -> int:
    """Exit 0; a bad input raises (FileNotFoundError, ValueError: PlaceError, DatasetError),
    which ``cli.main`` turns into exit 2 with ``comgs place: error: FILE: problem``."""
    name, sep, run = args.object.partition("=")
    if not sep or not name or not run:
        raise ValueError(f"--object must be NAME=RUN, got {args.object!r}")
    if args.at is not None and (args.pixel is not None or args.view is not None):
        raise ValueError("give --view VIEW --pixel X Y, or --at X Y Z, not both")
    if args.at is None and (args.pixel is None or args.view is None):
        raise ValueError("give --view VIEW --pixel X Y (or --at X Y Z)")
    cfg = PlaceConfig(**field_overrides(args, PlaceConfig))
    set_variant(args.mitsuba_variant)
    place(args.scene_run, name, run, args.out, view=args.view, pixel=args.pixel,
          at=args.at, cfg=cfg, say=print)
    return 0
