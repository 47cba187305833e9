"""Assembly of a Mitsuba scene of surfel shapes rendered by ``surfel_gbuffer``."""
from __future__ import annotations

import mitsuba as mi

from comgs_dr.surfels.params import SurfelParams
from comgs_dr.surfels.shape import SurfelShapeBase


def gbuffer_scene(surfels, sensors, environment=None, **integrator_props) -> mi.Scene:
    """A scene with surfel shapes, sensors and a ``surfel_gbuffer`` integrator.

    ``surfels``: a SurfelParams, a surfels shape, or a dict {id: either};
    ``sensors``: a sensor dict/object or a list of them;
    ``environment``: an emitter (dict or object) stored under the key ``environment``
    (seen with ``env_background=True``);
    ``integrator_props``: e.g. ``max_hits=16, targets="color,weight"``.
    """
    if not isinstance(surfels, dict):
        surfels = {"surfels": surfels}
    d = {"type": "scene", "integrator": {"type": "surfel_gbuffer", **integrator_props}}
    for key, s in surfels.items():
        d[key] = SurfelShapeBase.from_params(s, id=key) if isinstance(s, SurfelParams) else s
    if environment is not None:
        d["environment"] = environment
    if not isinstance(sensors, (list, tuple)):
        sensors = [sensors]
    for i, s in enumerate(sensors):
        d[f"sensor_{i:03d}"] = s
    return mi.load_dict(d)
