"""The command line: ``comgs view COMP_DIR [--host H] [--port P] [--res N] ...``
(``comgs_dr.view``). Register with ``_add_view(subparsers)``; viser is imported when the
command runs, not when the parser is built."""
from __future__ import annotations

from comgs_dr import set_variant
from comgs_dr.cli._flags import Spelling, add_config_flags, field_overrides
from comgs_dr.core.config import shared_options
from comgs_dr.lighting.scene_label import LABEL_CHOICES
from comgs_dr.stages.render_comp import VARIANTS
from comgs_dr.view.session import LIGHT_MODES, ViewConfig, ViewSession

SPELLINGS = {
    "host": Spelling(help="address the viewer listens on (0.0.0.0: every interface)"),
    "port": Spelling(help="port of the viewer (0: a free one, printed)"),
    "res": Spelling(metavar="N", help="size of the composite shown after each move, N×N px, "
                    "from the viewer's camera (its vertical field of view)"),
    "full_res": Spelling(metavar="N", help="size of 'render full size', N×N px (None: the "
                         "capture's width, at least --res)"),
    "variant": Spelling(choices=VARIANTS, help="composite shown first (the GUI switches it)"),
    "rays": Spelling(metavar="N", help="rays per pixel of the preview composite (None: the "
                     "integrator's 256)"),
    "full_rays": Spelling(metavar="N", help="rays per pixel of 'render full size'"),
    "light": Spelling(choices=LIGHT_MODES, help="estimate: a moved object is lit by the "
                      "estimate at its new centre (when the composition's light was "
                      "estimated); keep: it keeps its map"),
    "label": Spelling(choices=LABEL_CHOICES, help="scene label of that estimation (None: "
                      "auto)"),
    "pano": Spelling(metavar="W", help="panorama width of that estimation (height W/2)"),
    "sun_from_shadows": Spelling(choices=("auto", "off"), help="auto: that estimation also "
                                 "fits a sun to the scene's cast shadows (10-25 s a move)"),
    "points": Spelling(metavar="N", help="scene surfels shown as points, at most"),
    "placement": Spelling(metavar="transform.json", help="file 'save placement' writes "
                          "(None: COMP_DIR/transform.json); other objects' entries in it "
                          "are kept"),
}


def _add_view(sub) -> None:
    p = sub.add_parser(
        "view", parents=[shared_options(variant_alias=False)],
        help="web viewer of a composition: move objects with a gizmo, see the composite",
        description="Serve COMP_DIR (from `comgs compose`) in the browser (viser): the "
                    "scene and the objects as points, a transform gizmo on each object. On "
                    "a gizmo's release the edit stage re-runs for that object (its light at "
                    "the new placement, only the occlusion pairs it is part of) and the "
                    "composite is rendered from the viewer's camera at --res², with the "
                    "time it took. Buttons: save placement (transform.json in the scene "
                    "dataset's frame), render full size (COMP_DIR/view/full_*.png), the "
                    "variant (sop, trace, noshadow, paste). The composition folder is "
                    "updated in place by every move, as `comgs compose` would.")
    p.add_argument("comp_dir", metavar="COMP_DIR")
    add_config_flags(p, ViewConfig, SPELLINGS)
    p.set_defaults(func=_cmd_view)


def _cmd_view(args) -> int:
    cfg = ViewConfig(**field_overrides(args, ViewConfig))
    cfg.validate()
    set_variant(args.mitsuba_variant)
    session = ViewSession(args.comp_dir, cfg, say=(lambda *_: None) if args.quiet else print)
    from comgs_dr.view.app import serve             # viser: only when the viewer runs
    return serve(session, say=print)
