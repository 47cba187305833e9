"""The command line: ``comgs sfm PHOTOS|VIDEO --out DATA`` (structure from motion, COLMAP).

Flags come from :class:`~comgs_dr.stages.sfm.SfmConfig` (``core.config``), ``--out`` and
``--quiet`` from ``core.config.shared_options``. :func:`main` runs the command alone
(``python -m comgs_dr.cli.sfm``, tests); ``comgs sfm`` registers :func:`_add_sfm`.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from comgs_dr.core.config import (
    _parse_bool,
    add_config_arguments,
    config_overrides,
    numeric_problem,
    shared_options,
)
from comgs_dr.stages.sfm import (
    CAMERA_MODELS,
    CAMERA_MODES,
    MATCHING,
    SfmConfig,
    ensure_sfm,
    is_unposed_capture,
    reusable_output,
    run_sfm,
)
from comgs_dr.train.checkpoint import CKPT_NAME
from comgs_dr.data.photos import VIDEO_EXTENSIONS

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


# ----------------------------------------------------------------------------- inside other commands

#: the SfmConfig fields with a fixed set of values
CHOICES = {"matching": MATCHING, "camera_model": CAMERA_MODELS, "camera_mode": CAMERA_MODES}
#: ``dest`` of an SfmConfig field's flag inside another command (``sfm_max_size``)
PREFIX = "sfm_"


def add_sfm_flags(p: argparse.ArgumentParser, what: str = "DATA_DIR") -> None:
    """SfM flags for a command that also takes a folder of photos or a video (``comgs
    reconstruct PHOTOS``): ``--sfm-out DIR`` and one flag per scalar SfmConfig field, spelled
    as ``comgs sfm`` spells it (``--max-size``, ``--matching``) unless ``p`` already has that
    flag, then ``--sfm-<field>`` (``--sfm-seed``). Call it after the command's own flags."""
    taken = {s for a in p._actions for s in a.option_strings}
    g = p.add_argument_group(f"structure from motion (when {what} is a folder of photos or a "
                             "video: `comgs sfm` runs first)")
    g.add_argument("--sfm-out", dest="sfm_out", metavar="DIR", default=None,
                   help="where the SfM output goes (default OUT/sfm); an earlier complete one "
                        "of the same photos and settings is reused")
    defaults = SfmConfig()
    for f in dataclasses.fields(SfmConfig):
        default = getattr(defaults, f.name)
        tp = type(default)
        flag = "--" + f.name.replace("_", "-")
        flags = [flag] if flag not in taken else ["--sfm-" + f.name.replace("_", "-")]
        kw = dict(choices=CHOICES[f.name]) if f.name in CHOICES else dict(
            type=_parse_bool if tp is bool else tp, metavar=tp.__name__.upper())
        g.add_argument(*flags, dest=PREFIX + f.name, default=None,
                       help=f"`comgs sfm --{f.name.replace('_', '-')}` (default {default!r})",
                       **kw)


def sfm_flags_config(args) -> tuple[SfmConfig, list[str]]:
    """(the SfmConfig of :func:`add_sfm_flags`' flags, the fields typed); ValueError for a
    bad value, before any work."""
    typed = {f.name: getattr(args, PREFIX + f.name) for f in dataclasses.fields(SfmConfig)
             if getattr(args, PREFIX + f.name, None) is not None}
    return SfmConfig(**typed), sorted(typed)


def sfm_if_photos(source, out_dir, args, progress: bool = True) -> tuple[Path, dict | None]:
    """(the dataset to load, the SfM report or None): ``source`` itself when it is a dataset;
    for a folder of photos or a video (``stages.sfm.is_unposed_capture``) the SfM output in
    ``args.sfm_out`` or ``out_dir/sfm``, made by ``comgs sfm`` (or an earlier complete one
    reused), saying which on stdout."""
    cfg, typed = sfm_flags_config(args)
    sfm_out = getattr(args, "sfm_out", None)
    _check_source(Path(source))
    if not is_unposed_capture(source):
        if typed or sfm_out:
            print(f"note: {source} is a dataset with poses: the SfM flags "
                  f"({', '.join(['sfm_out'] * bool(sfm_out) + typed)}) are not used",
                  file=sys.stderr)
        return Path(source), None
    sfm_out = Path(sfm_out) if sfm_out else Path(out_dir) / "sfm"
    ckpt = Path(out_dir) / CKPT_NAME
    if ckpt.is_file():
        reusable, why = reusable_output(source, sfm_out, cfg)
        if reusable is None:
            raise ValueError(f"{ckpt}: a step-1 checkpoint, but the structure from motion in "
                             f"{sfm_out} would be made anew ({why}): its cameras would not "
                             "match the checkpoint's surfels. Choose a new --out, or delete "
                             "the checkpoint to start over")
    kind = "a video" if Path(source).is_file() else "photos without poses"
    say = (lambda s: print(s, flush=True)) if progress else (lambda s: None)
    report, reused = ensure_sfm(source, sfm_out, cfg, progress=progress, say=say)
    how = ("reused the earlier structure from motion in" if reused
           else "ran structure from motion (`comgs sfm`) into")
    print(f"{source} is {kind}: {how} {sfm_out}: {report['registered']}/{report['given']} "
          f"images registered, mean reprojection error "
          f"{report['mean_reprojection_error_px']:.3f} px"
          + ("" if reused else f", {report['seconds']['total']:.0f} s"), flush=True)
    return sfm_out, {**report, "reused": reused, "dir": str(sfm_out)}


def _check_source(p: Path) -> None:
    """ValueError naming ``p`` when it is neither a dataset, a folder of photos nor a video."""
    from comgs_dr.data.load import detect_format
    from comgs_dr.data.types import DatasetError
    what = ("a dataset folder (NeRF transforms, COLMAP, LLFF), a folder of photos or a video "
            f"({', '.join(VIDEO_EXTENSIONS)})")
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file or folder; give {what}")
    if p.is_file() and not is_unposed_capture(p) and p.suffix.lower() not in (".json", ".npy"):
        raise ValueError(f"{p}: not {what}")
    if p.is_dir() and not is_unposed_capture(p):
        try:
            detect_format(p)
        except DatasetError as e:
            raise ValueError(f"{e}; nor does it hold photos for `comgs sfm`") from None


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
