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




# ---------------------------------------------------------------------------------------
# Full pinhole intrinsics (fx, fy, cx, cy in pixels)

#: fx and fy closer than this (relative) make a plain ``perspective`` sensor (square pixels).
SQUARE_PIXEL_TOLERANCE = 1e-7
PINHOLE_PLUGIN = "comgs_pinhole"
_pinhole_variants: set[str] = set()


def pinhole(to_world, width: int, height: int, fx: float, fy: float, cx: float, cy: float,
            spp: int = 1, near_clip: float | None = None, far_clip: float | None = None) -> dict:
    """A sensor dict reproducing the OpenCV/COLMAP pinhole K = [[fx, 0, cx], [0, fy, cy],
    [0, 0, 1]] (pixels, corner-origin: pixel (i, j) covers [i, i+1] × [j, j+1]) of a
    ``width`` × ``height`` image, from a Mitsuba camera-to-world ``to_world`` (+X left,
    +Y up, +Z forward).

    Square pixels (fx = fy within ``SQUARE_PIXEL_TOLERANCE``): Mitsuba's ``perspective``
    with ``fov`` = 2 atan(W / 2fx) on x and ``principal_point_offset_x/y`` =
    (W/2 − cx)/W, (H/2 − cy)/H (Mitsuba adds them to the film position in [0, 1]² before
    un-projecting). fx ≠ fy: Mitsuba's perspective has square pixels only and refuses a
    scale in ``to_world``, so the ``comgs_pinhole`` sensor (registered here, in the active
    variant) un-projects pixel (u, v) to the camera direction (−(u − cx)/fx, −(v − cy)/fy,
    1) itself, with the perspective sensor's near/far-clip ray origins. Both are checked
    against K [R | t] in tests/test_real_cameras.py (< 1e-3 px).
    """
    fx, fy, cx, cy = map(float, (fx, fy, cx, cy))
    w, h = int(width), int(height)
    if w < 1 or h < 1:
        raise ValueError(f"pinhole: resolution must be positive, got {w}x{h}")
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise ValueError(f"pinhole: invalid intrinsics fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    clip = {k: float(v) for k, v in (("near_clip", near_clip), ("far_clip", far_clip))
            if v is not None}
    if abs(fx - fy) <= SQUARE_PIXEL_TOLERANCE * max(fx, fy):
        fov = float(np.degrees(2.0 * np.arctan(0.5 * w / fx)))
        d = from_matrix(to_world, fov, (w, h), spp)
        d["principal_point_offset_x"] = 0.5 - cx / w
        d["principal_point_offset_y"] = 0.5 - cy / h
        return {**d, **clip}
    register_pinhole()
    m = np.asarray(to_world, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"pinhole: expected a finite 4x4 matrix, got shape {m.shape}")
    return {"type": PINHOLE_PLUGIN, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "to_world": mi.ScalarTransform4f(m.tolist()),
            "sampler": {"type": "independent", "sample_count": int(spp)},
            "film": {"type": "hdrfilm", "width": w, "height": h,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"}, **clip}


def sensor_intrinsics(sensor) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in full-film pixels of a ``perspective`` or ``comgs_pinhole``
    sensor, measured from its rays (ValueError for another sensor)."""
    film = sensor.film()
    full = np.array(film.size(), np.float64)
    off, crop = np.array(film.crop_offset(), np.float64), np.array(film.crop_size(), np.float64)
    pos = np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]]) * full
    smp = (pos - off) / crop
    with dr.suspend_grad():
        ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(smp[:, 0], smp[:, 1]), mi.Point2f(0.5))
    d = np.array(ray.d, np.float64).reshape(3, -1).T
    m = np.asarray(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    c = d @ m[:3, :3]                                  # camera space (rows of R^T)
    if np.any(c[:, 2] <= 0):
        raise ValueError("sensor_intrinsics: the sensor's rays do not look forward")
    x, y = -c[:, 0] / c[:, 2], -c[:, 1] / c[:, 2]      # OpenCV: +X right, +Y down
    fx = (pos[1, 0] - pos[0, 0]) / (x[1] - x[0])
    fy = (pos[2, 1] - pos[0, 1]) / (y[2] - y[0])
    return float(fx), float(fy), float(pos[0, 0] - fx * x[0]), float(pos[0, 1] - fy * y[0])


def register_pinhole() -> None:
    """Register the ``comgs_pinhole`` sensor (fx ≠ fy) in the active variant (idempotent)."""
    variant = mi.variant()
    if variant in _pinhole_variants:
        return

    class PinholeCamera(mi.Sensor):
        """Pinhole with pixel intrinsics fx, fy, cx, cy (see :func:`pinhole`)."""

        def __init__(self, props):
            super().__init__(props)
            self.fx, self.fy = float(props["fx"]), float(props["fy"])
            self.cx, self.cy = float(props["cx"]), float(props["cy"])
            self.near_clip = float(props.get("near_clip", 0.01))
            self.far_clip = float(props.get("far_clip", 1e4))
            if not (self.fx > 0 and self.fy > 0 and 0 < self.near_clip < self.far_clip):
                raise ValueError(f"{PINHOLE_PLUGIN}: need fx, fy > 0 and 0 < near_clip < "
                                 f"far_clip")

        def _local(self, sample2):
            film = self.film()
            off = mi.ScalarVector2f(film.crop_offset())
            crop = mi.ScalarVector2f(film.crop_size())
            uv = off + mi.Vector2f(sample2) * crop                 # full-film pixels
            return dr.normalize(mi.Vector3f(-(uv.x - self.cx) / self.fx,
                                            -(uv.y - self.cy) / self.fy, 1.0))

        def _ray(self, time, d):
            tw = self.world_transform()
            dw = tw @ d
            inv_z = dr.rcp(d.z)
            near_t, far_t = self.near_clip * inv_z, self.far_clip * inv_z
            o = tw @ mi.Point3f(0.0)
            return mi.Ray3f(o + dw * near_t, dw, far_t - near_t, time, [])

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            return self._ray(time, self._local(sample2)), mi.Spectrum(1.0)

        def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
            crop = mi.ScalarVector2f(self.film().crop_size())
            ray = mi.RayDifferential3f(self._ray(time, self._local(sample2)))
            rx = self._ray(time, self._local(mi.Vector2f(sample2) + mi.Vector2f(1.0 / crop.x, 0)))
            ry = self._ray(time, self._local(mi.Vector2f(sample2) + mi.Vector2f(0, 1.0 / crop.y)))
            ray.o_x, ray.o_y, ray.d_x, ray.d_y = rx.o, ry.o, rx.d, ry.d
            ray.has_differentials = True
            return ray, mi.Spectrum(1.0)

        def to_string(self):
            return (f"PinholeCamera[fx={self.fx}, fy={self.fy}, cx={self.cx}, cy={self.cy}, "
                    f"film={self.film()}]")

    mi.register_sensor(PINHOLE_PLUGIN, lambda props: PinholeCamera(props))
    _pinhole_variants.add(variant)
