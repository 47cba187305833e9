"""Dataset records of reconstruction step 1: cameras (Mitsuba convention), views, scenes.

Camera convention: ``to_world`` is Mitsuba's sensor camera-to-world
(camera space: +X left, +Y up, +Z forward). Pixel coordinates are continuous with the
top-left image corner at (0, 0) and pixel (i, j) covering [i, i+1] x [j, j+1] (COLMAP's
convention; Mitsuba's film position = pixel / (W, H)). Intrinsics map to Mitsuba as

    fov_x = 2 atan(W / (2 fx)),   principal_point_offset_x = 0.5 - cx / W,
                                  principal_point_offset_y = 0.5 - cy / H

(offsets in units of the film width/height; Mitsuba adds them to the film position
before un-projecting, so the optical axis hits film position 0.5 - offset). Mitsuba's
pinhole has square pixels: fy must equal fx.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from comgs_dr.core.cameras import from_matrix


class DatasetError(ValueError):
    """A dataset on disk is missing, malformed or unsupported (the message names the path)."""


# Right-multiply a camera-to-world of the named convention to get Mitsuba's ``to_world``.
MITSUBA_FROM_OPENGL = np.diag([-1.0, 1.0, -1.0, 1.0])   # GL: +X right, +Y up, +Z back
MITSUBA_FROM_OPENCV = np.diag([-1.0, -1.0, 1.0, 1.0])   # CV/COLMAP: +X right, +Y down, +Z fwd
# LLFF columns are [down, right, back]: Mitsuba left = -right, up = -down, fwd = -back.
MITSUBA_FROM_LLFF = np.array([[0.0, -1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0],
                              [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])

#: Largest relative difference of fx and fy accepted (Mitsuba has no anisotropic pinhole).
FOCAL_TOLERANCE = 0.01
#: Largest deviation of a pose's rotation block from orthonormal that is silently repaired.
RIGID_TOLERANCE = 1e-2
#: A camera farther than this from the origin (any units) is a damaged file, not a capture:
#: at 1e200 the bounds overflowed to an infinite extent and the loader went on silently.
MAX_TRANSLATION = 1e12
#: Sensor clip planes × the scene extent. Mitsuba's defaults (0.01 and 1e4) are absolute:
#: a millimetre-scale scene was clipped away whole (an empty render, no error).
CLIP_FRACS = (1e-4, 1e4)


def clip_planes(extent: float) -> dict:
    """``near_clip``/``far_clip`` of a sensor for a scene of size ``extent`` (any units)."""
    e = float(extent)
    if not (np.isfinite(e) and e > 0):
        raise ValueError(f"clip_planes: the scene extent must be finite and > 0, got {extent!r}")
    return {"near_clip": CLIP_FRACS[0] * e, "far_clip": CLIP_FRACS[1] * e}


@dataclass
class Camera:
    """A pinhole camera in Mitsuba's convention (see the module docstring)."""
    to_world: np.ndarray                  # [4, 4] float64 camera-to-world, rigid
    width: int
    height: int
    fov_x_deg: float                      # horizontal field of view
    principal_point_offset_x: float = 0.0  # units of the image width
    principal_point_offset_y: float = 0.0  # units of the image height
    fy_over_fx: float = 1.0   # as calibrated (step 1 renders fx = fy; render-comp uses fy)

    def __post_init__(self):
        self.to_world = np.asarray(self.to_world, dtype=np.float64).reshape(4, 4)
        self.width, self.height = int(self.width), int(self.height)
        if self.width < 1 or self.height < 1:
            raise ValueError(f"Camera: resolution must be positive, got {self.width}x{self.height}")
        if not 0.0 < float(self.fov_x_deg) < 180.0:
            raise ValueError(f"Camera: fov_x_deg must be in (0, 180), got {self.fov_x_deg}")

    @classmethod
    def from_intrinsics(cls, to_world, width: int, height: int, fx: float, fy: float,
                        cx: float, cy: float, where: str = "camera") -> "Camera":
        """Camera from pixel intrinsics (OpenCV/COLMAP K, corner-origin pixels).

        ``where`` names the source in error messages (DatasetError when fx and fy differ by
        more than ``FOCAL_TOLERANCE`` or are not positive and finite).
        """
        fx, fy, cx, cy = map(float, (fx, fy, cx, cy))
        if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
            raise DatasetError(f"{where}: invalid intrinsics fx={fx}, fy={fy}, cx={cx}, cy={cy}")
        if abs(fx - fy) > FOCAL_TOLERANCE * max(fx, fy):
            raise DatasetError(
                f"{where}: fx={fx:.4g} and fy={fy:.4g} differ by more than "
                f"{FOCAL_TOLERANCE:.0%}; Mitsuba's perspective sensor has square pixels only "
                "(resample the images to square pixels)")
        fov = math.degrees(2.0 * math.atan(0.5 * width / fx))
        if not 0.0 < fov < 180.0:    # fx vanishing (e.g. 1e-300) next to the width
            raise DatasetError(f"{where}: focal length fx={fx:.4g} px gives a {fov:.6g}° field "
                               f"of view for a {width} px wide image (expected (0, 180))")
        return cls(to_world, width, height, fov, 0.5 - cx / width, 0.5 - cy / height, fy / fx)

    # ------------------------------------------------------------------ intrinsics
    @property
    def fx(self) -> float:
        """Focal length in pixels (fx = fy)."""
        return 0.5 * self.width / math.tan(math.radians(self.fov_x_deg) / 2.0)

    @property
    def cx(self) -> float:
        return (0.5 - self.principal_point_offset_x) * self.width

    @property
    def cy(self) -> float:
        return (0.5 - self.principal_point_offset_y) * self.height

    def intrinsics(self) -> np.ndarray:
        """OpenCV calibration matrix K [3, 3] (corner-origin pixels)."""
        f = self.fx
        return np.array([[f, 0.0, self.cx], [0.0, f, self.cy], [0.0, 0.0, 1.0]])

    @property
    def center(self) -> np.ndarray:
        """Camera position [3] in world space."""
        return self.to_world[:3, 3].copy()

    def world_to_camera_cv(self) -> np.ndarray:
        """World-to-camera [4, 4] in the OpenCV frame (+X right, +Y down, +Z forward)."""
        return np.linalg.inv(self.to_world @ MITSUBA_FROM_OPENCV)

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [N, 2] and depths along +Z [N] of world points [N, 3]."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        w2c = self.world_to_camera_cv()
        pc = p @ w2c[:3, :3].T + w2c[:3, 3]                   # [N, 3] OpenCV camera space
        uv = pc @ self.intrinsics().T                          # [N, 3]
        return uv[:, :2] / uv[:, 2:3], pc[:, 2]

    def sensor_dict(self, spp: int = 1, near_clip: float | None = None,
                    far_clip: float | None = None) -> dict:
        """Mitsuba ``perspective`` sensor dict (box filter, rgb hdrfilm, principal point)."""
        d = from_matrix(self.to_world, self.fov_x_deg, (self.width, self.height), spp)
        d["principal_point_offset_x"] = float(self.principal_point_offset_x)
        d["principal_point_offset_y"] = float(self.principal_point_offset_y)
        if near_clip is not None:
            d["near_clip"] = float(near_clip)
        if far_clip is not None:
            d["far_clip"] = float(far_clip)
        return d


@dataclass
class View:
    """One posed image. ``image`` holds the stored (sRGB display) values, not linearised."""
    name: str
    camera: Camera
    image: np.ndarray                     # [H, W, 3] float32 in [0, 1]
    mask: np.ndarray | None = None        # [H, W] float32 in [0, 1] (alpha / object mask)
    path: str = ""

    def __post_init__(self):
        hw = (self.camera.height, self.camera.width)
        if self.image.shape != (*hw, 3):
            raise ValueError(f"View {self.name}: image shape {self.image.shape} != {(*hw, 3)}")
        if self.mask is not None and self.mask.shape != hw:
            raise ValueError(f"View {self.name}: mask shape {self.mask.shape} != {hw}")


@dataclass
class SceneData:
    """A loaded dataset: train/test views, optional initial points, scene bounds.

    ``bounds`` = (center [3], radius): the sphere around the camera centres enlarged by
    10% (3DGS's "cameras extent", used to scale densification and learning rates); with a
    single camera position the points' extent, else radius 1. ``world_from_source`` [4, 4]
    maps the dataset's own world frame to ours (e.g. the ``up="auto"`` rotation).
    """
    train: list[View]
    test: list[View]
    points: np.ndarray | None = None      # [P, 3] float32 world positions
    colors: np.ndarray | None = None      # [P, 3] float32 in [0, 1]
    white_background: bool = False
    bounds: tuple[np.ndarray, float] | None = None
    source: str = ""
    world_from_source: np.ndarray = field(default_factory=lambda: np.eye(4))
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.bounds is None:
            self.bounds = compute_bounds([v.camera for v in self.train + self.test], self.points)

    def clip_planes(self) -> dict:
        """Sensor clip planes for this scene's size (:func:`clip_planes` of the bounds)."""
        return clip_planes(max(float(self.bounds[1]), 1e-6))

    @property
    def background(self) -> np.ndarray:
        """Background colour [3] the images were composited onto."""
        return np.full(3, 1.0 if self.white_background else 0.0, np.float32)

    @property
    def views(self) -> list[View]:
        return self.train + self.test


# ---------------------------------------------------------------------------- helpers

def compute_bounds(cameras: list[Camera], points=None) -> tuple[np.ndarray, float]:
    """(center [3], radius) of the camera centres (x1.1), see :class:`SceneData`."""
    c = np.array([cam.center for cam in cameras]).reshape(-1, 3)
    center = c.mean(0) if len(c) else np.zeros(3)
    radius = 1.1 * float(np.linalg.norm(c - center, axis=1).max()) if len(c) else 0.0
    if radius <= 1e-9 and points is not None and len(points):
        p = np.asarray(points, np.float64)
        center = p.mean(0)
        radius = 1.1 * float(np.linalg.norm(p - center, axis=1).max())
    return center, (radius if radius > 1e-9 else 1.0)


def rigid_pose(m, where: str) -> np.ndarray:
    """Validate a 3x4/4x4 rigid transform and return it as float64 [4, 4], rotation block
    re-orthonormalised. DatasetError (naming ``where``) for non-finite, singular, mirrored,
    scaled/sheared or projective matrices."""
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise DatasetError(f"{where}: pose is not a numeric matrix ({e})") from None
    if a.shape not in ((3, 4), (4, 4)):
        raise DatasetError(f"{where}: pose must be 3x4 or 4x4, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"{where}: pose has non-finite entries")
    if np.abs(a[:3, 3]).max() > MAX_TRANSLATION:
        raise DatasetError(f"{where}: pose translation {a[:3, 3].tolist()} is beyond "
                           f"{MAX_TRANSLATION:g} scene units (a damaged file?)")
    if a.shape == (4, 4) and not np.allclose(a[3], [0, 0, 0, 1], atol=1e-6):
        raise DatasetError(f"{where}: pose's last row is {a[3].tolist()}, not [0, 0, 0, 1]")
    r = a[:3, :3]
    u, s, vt = np.linalg.svd(r)
    if s.min() < 1e-8 * max(s.max(), 1e-300):
        raise DatasetError(f"{where}: pose is not invertible (singular rotation block)")
    if np.linalg.det(r) < 0:
        raise DatasetError(f"{where}: pose is a reflection (det < 0), not a rotation")
    if np.abs(s - 1.0).max() > RIGID_TOLERANCE:
        raise DatasetError(f"{where}: pose is not rigid (rotation block has singular values "
                           f"{np.round(s, 4).tolist()}); scaled/sheared cameras are unsupported")
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = u @ vt, a[:3, 3]
    return out


def rotation_to_z(u) -> np.ndarray:
    """Smallest rotation [3, 3] taking unit vector ``u`` to +Z."""
    u = np.asarray(u, np.float64) / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c < -1.0 + 1e-12:                    # antiparallel: half turn about X
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(u, z)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def up_alignment(to_worlds: list[np.ndarray], up: str, where: str) -> np.ndarray:
    """World rotation [4, 4] for ``up``: "auto" sends the mean camera up (Mitsuba +Y,
    i.e. OpenCV -Y) to +Z; "none" is the identity."""
    if up not in ("auto", "none"):
        raise ValueError(f"{where}: up must be 'auto' or 'none', got {up!r}")
    t = np.eye(4)
    if up == "none" or not to_worlds:
        return t
    mean_up = np.mean([m[:3, 1] for m in to_worlds], axis=0)
    if np.linalg.norm(mean_up) < 1e-6:
        warnings.warn(f"{where}: camera up vectors cancel out; keeping the dataset's frame")
        return t
    t[:3, :3] = rotation_to_z(mean_up)
    return t


def holdout(n: int, test_every: int | None) -> tuple[list[int], list[int]]:
    """LLFF-style split of ``n`` ordered items: indices i % test_every == 0 are test."""
    if not test_every:
        return list(range(n)), []
    if int(test_every) < 1:
        raise ValueError(f"test_every must be >= 1 or None, got {test_every}")
    test = [i for i in range(n) if i % int(test_every) == 0]
    return [i for i in range(n) if i % int(test_every) != 0], test


def aligned_split(frames: list[dict], up: str, where: str, test_every: int | None):
    """Rotate frame poses by the ``up`` alignment and hold out every ``test_every``-th frame.

    Returns (rotation [4, 4], train indices, test indices); refuses an empty train split.
    """
    rot = up_alignment([f["to_world"] for f in frames], up, where)
    for f in frames:
        f["to_world"] = rot @ f["to_world"]
    tr, te = holdout(len(frames), test_every)
    if not tr:
        raise DatasetError(f"{where}: no training images left after holding out every "
                           f"{test_every}th image ({len(frames)} images)")
    return rot, tr, te


def subsample(items: list, max_views: int | None) -> list:
    """At most ``max_views`` items, evenly spaced (all when None)."""
    if max_views is None or len(items) <= int(max_views):
        return list(items)
    if int(max_views) < 1:
        raise ValueError(f"max_views must be >= 1 or None, got {max_views}")
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, int(max_views))).astype(int))
    return [items[i] for i in idx]


def project(camera, pts: np.ndarray):
    """Pinhole projection into a :class:`Camera` (Mitsuba convention): (x_px, y_px, in_front & inside)."""
    m = np.linalg.inv(np.asarray(camera.to_world, float))            # world -> camera
    pc = pts @ m[:3, :3].T + m[:3, 3]                                  # [N, 3], +Z forward, +X left
    w, h = camera.width, camera.height
    f = 0.5 * w / np.tan(np.radians(camera.fov_x_deg) / 2)
    z = np.maximum(pc[:, 2], 1e-9)
    cx = w * (0.5 - getattr(camera, "principal_point_offset_x", 0.0))   # Mitsuba: cx = (0.5 − off_x)·W
    cy = h * (0.5 - getattr(camera, "principal_point_offset_y", 0.0))
    x = cx - f * pc[:, 0] / z                                          # +X is left in Mitsuba
    y = cy - f * pc[:, 1] / z                                          # +Y is up
    ok = (pc[:, 2] > 1e-6) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return x, y, ok
