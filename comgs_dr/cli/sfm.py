"""The command line: ``comgs sfm PHOTOS|VIDEO --out DATA`` (structure from motion, COLMAP).

Flags come from :class:`~comgs_dr.stages.sfm.SfmConfig` (``core.config``), ``--out`` and
``--quiet`` from ``core.config.shared_options``. :func:`main` runs the command alone
(``python -m comgs_dr.cli.sfm``, tests); ``comgs sfm`` registers :func:`_add_sfm`.
"""
from __future__ import annotations

import argparse
import sys

from comgs_dr.core.config import (
    add_config_arguments,
    config_overrides,
    numeric_problem,
    shared_options,
)
from comgs_dr.stages.sfm import CAMERA_MODELS, CAMERA_MODES, MATCHING, SfmConfig, run_sfm

DESCRIPTION = (
    "Camera poses and sparse points from a folder of photos or a video (.mp4/.mov) with "
    "COLMAP (pycolmap): SIFT features, exhaustive or sequential matching, incremental "
    "mapping, the largest model undistorted to PINHOLE cameras. Writes DATA/images, "
    "DATA/sparse/0 (what `comgs reconstruct DATA` reads), DATA/sfm.json (registered "
    "images, reprojection error, points, seconds per phase) and DATA/distorted (the "
    "prepared images, the COLMAP database and every raw model). Every scalar field of "
    "SfmConfig is a flag.")
#: ``--out`` of ``shared_options``
OUT = dict(required=True, metavar="DATA",
           help="output COLMAP folder (new, empty or an earlier `comgs sfm` output)")


def _add_sfm(sub) -> None:
    """``comgs sfm``: parser of the subcommand (``sub``: the subparsers action)."""
    p = sub.add_parser(
        "sfm", parents=[shared_options(out=OUT, mitsuba_variant=False)],
        help="camera poses and points from photos or a video (COLMAP)", description=DESCRIPTION)
    _add_arguments(p)
    p.set_defaults(func=_cmd_sfm)


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", metavar="PHOTOS|VIDEO",
                   help="a folder of photos (.jpg, .png, ...) or a video file (.mp4, .mov, ...)")
    # fields with a fixed set of values: spelled by hand so that --help lists the choices
    p.add_argument("--matching", choices=MATCHING, default=None,
                   help="auto: exhaustive up to --exhaustive-max images, sequential for a "
                        "video or more images (default auto)")
    p.add_argument("--camera-model", dest="camera_model", choices=CAMERA_MODELS, default=None,
                   help="COLMAP camera model before undistortion (default SIMPLE_RADIAL)")
    p.add_argument("--camera-mode", dest="camera_mode", choices=CAMERA_MODES, default=None,
                   help="one camera for all images or one per image (default auto)")
    add_config_arguments(p, SfmConfig)


def _cmd_sfm(args) -> int:
    cfg = SfmConfig(**config_overrides(args, SfmConfig))      # flags checked before any work
    r = run_sfm(args.source, args.out, cfg, progress=not args.quiet)
    print(f"sfm done: {r['registered']}/{r['given']} images registered, mean reprojection "
          f"error {r['mean_reprojection_error_px']:.3f} px, {r['points']} points, "
          f"{r['seconds']['total']:.0f} s -> {args.out} (sfm.json)")
    if r.get("dropped_images"):
        print(f"  not registered: {len(r['dropped_images'])} image(s), listed in sfm.json "
              "(dropped_images)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run ``comgs sfm`` alone; returns the exit code (2: usage or input errors, with the
    file and the problem on stderr, never a traceback)."""
    parser = argparse.ArgumentParser(
        prog="comgs sfm", description=DESCRIPTION,
        parents=[shared_options(out=OUT, mitsuba_variant=False)])
    _add_arguments(parser)
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:          # --help (0) or a usage error (2)
        return int(e.code or 0)
    problem = numeric_problem(parser, args)
    if problem:
        print(f"comgs sfm: error: {problem}", file=sys.stderr)
        return 2
    try:
        return _cmd_sfm(args)
    except (FileNotFoundError, ValueError, ImportError) as e:
        print(f"comgs sfm: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:             # full disk, unwritable folder
        print(f"comgs sfm: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
