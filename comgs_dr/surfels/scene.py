"""Assembly of a Mitsuba scene of surfel shapes rendered by ``surfel_gbuffer``."""
from __future__ import annotations

import mitsuba as mi

from comgs_dr.surfels.params import SurfelParams
from comgs_dr.surfels.shape import SurfelShapeBase


def gbuffer_scene(surfels, sensors, **integrator_props) -> mi.Scene:
    """A scene with surfel shapes, sensors and a ``surfel_gbuffer`` integrator.

    ``surfels``: a SurfelParams, a surfels shape, or a dict {id: either};
    ``sensors``: a sensor dict/object or a list of them;
    ``integrator_props``: e.g. ``max_hits=16, targets="color,weight"``.
    """
    if not isinstance(surfels, dict):
        surfels = {"surfels": surfels}
    d = {"type": "scene", "integrator": {"type": "surfel_gbuffer", **integrator_props}}
    for key, s in surfels.items():
        d[key] = SurfelShapeBase.from_params(s, id=key) if isinstance(s, SurfelParams) else s
    if not isinstance(sensors, (list, tuple)):
        sensors = [sensors]
    for i, s in enumerate(sensors):
        d[f"sensor_{i:03d}"] = s
    return mi.load_dict(d)
