"""The ``comgs`` command line. ``comgs COMMAND --help`` lists a command's flags.

Commands (``_SUBCOMMANDS``, in this order; tests/test_config_cli.py checks this list
against the parser):

    sfm                camera poses from photos or a video (pycolmap) -> a COLMAP folder
    make-dataset       render synthetic ground truth: object, scene, llff, composition
    demo               the whole pipeline on embedded procedural inputs
    report             one self-contained HTML report of a run folder
    reconstruct        step 1: surfel radiance and geometry from images
    render             render a reconstruction run and write metrics
    export-mesh        a triangle mesh of a reconstruction
    cut                the object standing on a support plane, cut out of a scene run
    decompose          step 2: materials, env map and SOPs from a step-1 run
    relight            render a step-2 run under a new environment map
    estimate-light     an HDR environment map at a placement in a surfel scene
    compare-light      score an estimated map against the true light
    train-completion   train the panorama completion network
    train-light-head   train the light head (power of clipped lights)
    train-scene-label  train the indoor/outdoor classifier
    place              stand an object on the scene's surface at a pixel -> transform.json
    compose            place objects in a scene, light them, cache occlusion
    render-comp        render a composition along cameras or a dataset's test views
    view               web viewer: move objects with a gizmo, see the composite (viser)
    batch              run a jobs file (reconstruct ... render-comp) as a Ray task graph

Each command has a parser builder ``_add_<name>(subparsers)`` in one of the modules of this
package (``datasets``, ``objects``, ``lighting``, ``composition``) that sets
``func=_cmd_<name>``; ``_cmd_<name>(args)`` returns an exit code. Flags come from each
command's config dataclass (``core.config``, ``cli._flags``); ``--out``,
``--mitsuba-variant`` and ``--quiet`` from ``core.config.shared_options``.
"""
from __future__ import annotations

import argparse
import sys

from comgs_dr.cli.batch import _add_batch
from comgs_dr.cli.composition import _add_compose, _add_render_comp
from comgs_dr.cli.cut import _add_cut
from comgs_dr.cli.datasets import _add_demo, _add_make_dataset, _add_report
from comgs_dr.cli.lighting import (
    _add_compare_light,
    _add_estimate_light,
    _add_train_completion,
    _add_train_light_head,
    _add_train_scene_label,
)
from comgs_dr.cli.objects import (
    _add_decompose,
    _add_export_mesh,
    _add_reconstruct,
    _add_relight,
    _add_render,
)
from comgs_dr.cli.place import _add_place
from comgs_dr.cli.sfm import _add_sfm
from comgs_dr.cli.view import _add_view
from comgs_dr.core.config import numeric_problem
from comgs_dr.train.interrupt import TrainingInterrupted

_SUBCOMMANDS = (_add_sfm, _add_make_dataset, _add_demo, _add_report, _add_reconstruct,
                _add_render, _add_export_mesh, _add_cut, _add_decompose, _add_relight, _add_estimate_light, _add_compare_light,
                _add_train_completion, _add_train_light_head, _add_train_scene_label,
                _add_place, _add_compose, _add_render_comp, _add_view, _add_batch)

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
    except RuntimeError as e:            # mi.render wraps a plugin's error in its custom op
        cause = input_cause(e)
        if cause is None:
            raise
        print(f"comgs {args.command}: error: {cause}", file=sys.stderr)
        return 2


def input_cause(exc: BaseException) -> BaseException | None:
    """The input error (FileNotFoundError, ValueError, ImportError) that caused ``exc``, or
    None: Dr.Jit re-raises an exception of ``mi.render``'s custom op as a RuntimeError
    ("error while performing a custom differentiable operation") whose cause is the plugin's."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, (FileNotFoundError, ValueError, ImportError)):
            return exc
        exc = exc.__cause__ or (None if exc.__suppress_context__ else exc.__context__)
    return None
