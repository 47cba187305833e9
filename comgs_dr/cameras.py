"""Small helpers to build Mitsuba sensors and G-buffer scenes from Python."""
from __future__ import annotations

import mitsuba as mi


def perspective(origin, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov: float = 40.0,
                res: int | tuple[int, int] = 64, spp: int = 1) -> dict:
    """A ``perspective`` sensor dict looking from ``origin`` at ``target`` (Z-up, box filter).

    ``res`` is an int (square) or (width, height); ``fov`` is the horizontal field of view.
    """
    w, h = (res, res) if isinstance(res, int) else res
    if w < 1 or h < 1:
        raise ValueError(f"perspective: resolution must be positive, got {w}x{h}")
    return {
        "type": "perspective", "fov": float(fov), "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=list(map(float, origin)),
                                                   target=list(map(float, target)),
                                                   up=list(map(float, up))),
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": int(w), "height": int(h),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    }


def gbuffer_scene(surfels, sensors, **integrator_props) -> mi.Scene:
    """A scene with surfel shapes, sensors and a ``surfel_gbuffer`` integrator.

    ``surfels``: a SurfelParams, a surfels shape, or a dict {id: either};
    ``sensors``: a sensor dict/object or a list of them;
    ``integrator_props``: e.g. ``max_hits=16, targets="color,weight"``.
    """
    from .surfels.params import SurfelParams
    from .surfels.shape import SurfelShapeBase
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


def from_matrix(to_world, fov_x_deg: float, res: int | tuple[int, int], spp: int = 1) -> dict:
    """A ``perspective`` sensor dict from a Mitsuba camera-to-world 4x4 (+Z forward)."""
    import numpy as np
    m = np.asarray(to_world, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"from_matrix: expected a finite 4x4 matrix, got shape {m.shape}")
    w, h = (res, res) if isinstance(res, int) else res
    return {
        "type": "perspective", "fov": float(fov_x_deg), "fov_axis": "x",
        "to_world": mi.ScalarTransform4f(m.tolist()),
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": int(w), "height": int(h),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    }
