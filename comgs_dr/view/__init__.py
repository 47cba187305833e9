"""``comgs view COMP_DIR``: an interactive web viewer of a composition (viser).

Layer: above ``stages`` (it drives ``stages.compose``, ``stages.render_comp`` and
``stages.estimate_light``, which may not import each other), below ``cli``.

* :mod:`comgs_dr.view.session` — :class:`ViewSession`, the work without a browser: move an
  object (re-run the edit stage for it: its lighting at the new placement, only the
  occlusion pairs it is part of), render the composite from a camera, save the placements.
* :mod:`comgs_dr.view.app` — :class:`ViewerApp`, the viser server: the scene and the objects
  as points, a transform gizmo on each object, the composite in the GUI.
"""
from comgs_dr.view.session import ViewConfig, ViewSession

__all__ = ["ViewConfig", "ViewSession"]
