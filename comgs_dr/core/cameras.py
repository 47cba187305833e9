"""Cameras: Mitsuba ``perspective`` sensor dicts and the pixel-centre rays of any sensor."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def perspective(origin, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov: float = 40.0,
                res: int | tuple[int, int] = 64, spp: int = 1) -> dict:
    """A ``perspective`` sensor dict looking from ``origin`` at ``target`` (Z-up, box filter).

    ``res`` is an int (square) or (width, height); ``fov`` is the horizontal field of view.
    Looking along ``up`` (a top-down view), the up vector becomes +Y, or +X when the view
    runs along Y (a look-at with the view direction parallel to up has no defined roll: its
    matrix was NaN and every render through it NaN). ValueError when ``origin`` equals
    ``target``, or any of the three is not finite, or ``up`` is zero.
    """
    w, h = (res, res) if isinstance(res, int) else res
    if w < 1 or h < 1:
        raise ValueError(f"perspective: resolution must be positive, got {w}x{h}")
    o, t, u = (np.asarray(v, np.float64).reshape(3) for v in (origin, target, up))
    d = t - o
    if not (np.isfinite(o).all() and np.isfinite(t).all()) or not np.linalg.norm(d) > 0:
        raise ValueError(f"perspective: origin {o.tolist()} and target {t.tolist()} must be "
                         f"finite and distinct")
    if not (np.isfinite(u).all() and np.linalg.norm(u) > 0):
        raise ValueError(f"perspective: up {u.tolist()} must be finite and non-zero")
    if np.linalg.norm(np.cross(d / np.linalg.norm(d), u / np.linalg.norm(u))) < 1e-6:
        u = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.5 * np.linalg.norm(d) else np.array([1.0, 0.0, 0.0])
    origin, target, up = o, t, u
    return {
        "type": "perspective", "fov": float(fov), "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=list(map(float, origin)),
                                                   target=list(map(float, target)),
                                                   up=list(map(float, up))),
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": int(w), "height": int(h),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    }




def from_matrix(to_world, fov_x_deg: float, res: int | tuple[int, int], spp: int = 1) -> dict:
    """A ``perspective`` sensor dict from a Mitsuba camera-to-world 4x4 (+Z forward)."""
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


def camera_rays(sensor_or_dict, width: int | None = None, height: int | None = None):
    """Unit ray directions and origins through pixel centres: (dirs, origins), each
    ``mi.TensorXf`` [H, W, 3] (no AD).

    Rays are ``sensor.sample_ray(shutter_open, 0, ((x+½)/W, (y+½)/H), aperture centre)``,
    exactly the deterministic rays of the ``surfel_gbuffer`` integrator, so any Mitsuba
    sensor works (principal point offsets, thin lens at its centre, orthographic).
    Origins are per pixel: Mitsuba's perspective rays start on the near-clip plane,
    o = o_cam + t_near·d (t_near = near_clip / cos), and the G-buffer depth is measured
    from there — pass these origins to ``depth_to_normal``, not the camera centre.
    Without ``width``/``height`` the film's crop window is used: Mitsuba's projective
    sensors map ``sample2`` ∈ [0, 1]² onto the crop window, so pixel (x, y) of the full
    film is ``((x + ½ − crop_x) / crop_w, …)``, as ``mi.render`` does.
    """
    sensor = mi.load_dict(sensor_or_dict) if isinstance(sensor_or_dict, dict) else sensor_or_dict
    if not isinstance(sensor, mi.Sensor):
        raise ValueError(f"camera_rays: expected a Mitsuba sensor or sensor dict, "
                         f"got {type(sensor_or_dict).__name__}")
    m = np.asarray(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    if not np.isfinite(m).all():
        raise ValueError(f"camera_rays: the sensor's to_world is not finite (a look-at along "
                         f"its up vector?): {np.round(m, 3).tolist()}")
    film = sensor.film()
    if width is None and height is None:
        (w, h), off = film.crop_size(), film.crop_offset()
    elif width is None or height is None:
        raise ValueError("camera_rays: give both width and height, or neither")
    else:
        w, h, off = int(width), int(height), (0, 0)
        if w < 1 or h < 1:
            raise ValueError(f"camera_rays: resolution must be positive, got {w}x{h}")
    with dr.suspend_grad():
        idx = dr.arange(mi.UInt32, w * h)
        pos = mi.Vector2f(mi.Float(idx % w), mi.Float(idx // w)) + 0.5    # within the crop
        aperture = mi.Vector2f(0.5)
        ray, _ = sensor.sample_ray(time=sensor.shutter_open(), sample1=0.0,
                                   sample2=pos / mi.ScalarVector2f(w, h), sample3=aperture)
        d = dr.normalize(mi.Vector3f(ray.d))                               # [H·W]
        o = mi.Vector3f(ray.o)
        dirs = mi.TensorXf(dr.ravel(d), shape=(h, w, 3))
        origins = mi.TensorXf(dr.ravel(o), shape=(h, w, 3))
        dr.eval(dirs, origins)
    return dirs, origins


