"""COLMAP datasets: a sparse model (binary or text, read with pycolmap) + images.

COLMAP stores world-to-camera poses in OpenCV's camera frame (+X right, +Y down,
+Z forward): ``to_world = inv([R | t]) @ diag(-1, -1, 1, 1)``. Pixel coordinates share
our corner-origin convention, so (fx, fy, cx, cy) map to Mitsuba unchanged (see
``data_types``). COLMAP's world has no preferred up axis: ``up="auto"`` rotates the world
about the origin by the smallest rotation taking the mean camera up vector (OpenCV -Y,
i.e. Mitsuba +Y) to +Z, applied to cameras and points alike (recorded in
``SceneData.world_from_source``); ``up="none"`` keeps COLMAP's frame.
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from comgs_dr.data.images import (
    IMAGE_EXTENSIONS,
    check_scale,
    load_view,
    missing_error,
    scaled_intrinsics,
)
from comgs_dr.data.types import (
    MITSUBA_FROM_OPENCV,
    DatasetError,
    SceneData,
    aligned_split,
    rigid_pose,
    subsample,
)

#: Pinhole-family models; the ones with distortion parameters are accepted only when the
#: distortion moves no border pixel by more than ``MAX_DISTORTION_PX``.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV",
                  "FULL_OPENCV")
MAX_DISTORTION_PX = 0.1
_MODEL_FILES = ("cameras.bin", "cameras.txt")


def load_colmap(root, images: str = "images", masks: str | None = None,
                resolution_scale: int = 1, test_every: int = 8, up: str = "auto",
                max_views: int | None = None, white_background: bool = False,
                pixels: bool = True) -> SceneData:
    """Load a COLMAP scene: model at ``root/sparse/0`` or ``root/sparse``, images in
    ``root/images`` (folder name or absolute path; files may be resized copies, e.g.
    ``images_2``: intrinsics follow the file size).

    Registered images sorted by name; every ``test_every``-th (0, 8, ...) is test
    (None/0: no test split). ``masks``: folder of masks named like the images (same stem,
    any image extension, or COLMAP's ``<name>.png``); 0/255 -> 0/1. Points3D become
    ``points``/``colors``. Images with alpha are composited onto white/black
    (``white_background``), the alpha becoming the mask unless ``masks`` is given.
    Raises DatasetError naming the offending path.
    """
    root, k = Path(root), check_scale(resolution_scale)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    model_dir = _model_dir(root)
    rec = _read_model(model_dir)
    image_dir = root / images
    if not image_dir.is_dir():
        raise DatasetError(f"{image_dir}: image folder not found")
    try:
        regs = sorted((im for im in rec.images.values() if _has_pose(im)), key=lambda im: im.name)
    except UnicodeDecodeError as e:
        raise DatasetError(f"{model_dir}: an image name is not UTF-8 text ({e})") from None
    if not regs:
        raise DatasetError(f"{model_dir}: the model has no registered images")

    cams = {cid: _intrinsics(c, f"{model_dir} camera {cid}") for cid, c in rec.cameras.items()}
    frames, missing = [], []
    for im in regs:
        where = f"{model_dir} image {im.image_id} ({im.name})"
        w2c = _cam_from_world(im)                              # [3, 4]
        c2w = np.linalg.inv(rigid_pose(np.vstack([w2c, [0, 0, 0, 1]]), where))
        path = image_dir / im.name
        if not path.is_file():
            missing.append(im.name)
        frames.append({"name": im.name, "path": path, "to_world": c2w @ MITSUBA_FROM_OPENCV,
                       "intrinsics": cams[im.camera_id]})
    if missing:
        raise missing_error(f"image files (in {image_dir})", model_dir,
                            missing, len(regs))
    mask_paths = _mask_paths(root, masks, [f["name"] for f in frames])

    rot, tr, te = aligned_split(frames, up, str(model_dir), test_every)
    points, colors = _points(rec, model_dir)
    if points is not None:
        points = (points @ rot[:3, :3].T).astype(np.float32)
    bg = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    load = lambda idx: [load_view(f["name"], f["path"], f["to_world"], f["intrinsics"], k, bg,
                                  mask_path=mask_paths.get(f["name"]), pixels=pixels)
                        for f in subsample([frames[i] for i in idx], max_views)]
    return SceneData(train=load(tr), test=load(te), points=points, colors=colors,
                     world_from_source=rot, white_background=bool(white_background),
                     source=f"colmap:{model_dir} ({image_dir.name}, test every {test_every}, "
                            f"up={up}, scale 1/{k})",
                     meta={"format": "colmap", "resolution_scale": k,
                           "masks": None if masks is None else str(root / masks)})


def _model_dir(root: Path) -> Path:
    for d in (root / "sparse" / "0", root / "sparse"):
        if any((d / f).is_file() for f in _MODEL_FILES):
            return d
    raise DatasetError(f"{root}: no COLMAP model (cameras.bin/.txt) in sparse/0 or sparse")


def _read_model(model_dir: Path):
    try:
        import pycolmap  # heavy: loaded only for COLMAP folders
    except ImportError as e:
        raise ImportError("load_colmap needs pycolmap (pip install pycolmap)") from e
    if all((model_dir / f).is_file() for f in ("cameras.bin", "images.bin", "points3D.bin")):
        check_binary_model(model_dir, _param_counts(pycolmap))
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError/IndexError/MemoryError
        raise DatasetError(f"{model_dir}: cannot read the COLMAP model ({e})") from None


def _param_counts(pycolmap) -> dict[int, int]:
    """{camera model id: number of parameters} of the installed COLMAP."""
    create = getattr(pycolmap.Camera, "create_from_model_id", None) or pycolmap.Camera.create
    out = {}
    for m in pycolmap.CameraModelId.__members__.values():
        if int(m.value) >= 0:
            out[int(m.value)] = len(create(1, m, 1.0, 1, 1).params)
    return out


class _BinReader:
    """Bounds-checked walk over one COLMAP ``.bin`` file (DatasetError naming it)."""

    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def take(self, fmt: str) -> tuple:
        n = struct.calcsize(fmt)
        if self.pos + n > len(self.data):
            raise DatasetError(f"{self.path}: truncated ({len(self.data)} bytes, a record "
                               f"at byte {self.pos} needs {n} more)")
        v = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += n
        return v

    def skip(self, n: int) -> None:
        self.fits(1, n, "record")
        self.pos += n

    def fits(self, count: int, min_size: int, what: str) -> int:
        left = len(self.data) - self.pos
        if count * min_size > left:
            raise DatasetError(f"{self.path}: claims {count} {what}(s) of at least {min_size} "
                               f"bytes but {left} bytes are left (corrupt or truncated)")
        return count

    def count(self, min_size: int, what: str) -> int:
        return self.fits(self.take("<Q")[0], min_size, what)

    def cstring(self) -> None:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise DatasetError(f"{self.path}: truncated (unterminated image name at byte "
                               f"{self.pos})")
        self.pos = end + 1


def check_binary_model(model_dir: Path, n_params: dict[int, int]) -> None:
    """Walk a binary COLMAP model's record structure before COLMAP reads it: a corrupted
    count made COLMAP loop for ~2^63 iterations (a hang) or abort on allocation.
    ``n_params``: {camera model id: parameter count}. DatasetError naming the file."""
    r = _BinReader(model_dir / "cameras.bin")
    for _ in range(r.count(24, "camera")):
        _, model = r.take("<Ii")
        if model not in n_params:
            raise DatasetError(f"{r.path}: unknown camera model id {model} at byte {r.pos - 4}")
        r.take("<QQ")
        r.skip(8 * n_params[model])
    r = _BinReader(model_dir / "images.bin")
    for _ in range(r.count(73, "image")):
        r.take("<I7dI")
        r.cstring()
        r.skip(24 * r.count(24, "2D point"))
    r = _BinReader(model_dir / "points3D.bin")
    for _ in range(r.count(51, "3D point")):
        r.take("<Q3d3Bd")
        r.skip(8 * r.count(8, "track element"))
    if (model_dir / "rigs.bin").is_file():
        r = _BinReader(model_dir / "rigs.bin")
        for _ in range(r.count(8, "rig")):
            _, n_sensors = r.take("<II")
            if n_sensors:
                r.take("<iI")
                for _ in range(r.fits(n_sensors - 1, 9, "rig sensor")):
                    if r.take("<iIB")[2]:
                        r.skip(56)
    if (model_dir / "frames.bin").is_file():
        r = _BinReader(model_dir / "frames.bin")
        for _ in range(r.count(68, "frame")):
            n_data = r.take("<II7dI")[-1]
            r.skip(16 * r.fits(n_data, 16, "frame data id"))


def _has_pose(im) -> bool:
    return bool(im.has_pose) if hasattr(im, "has_pose") else bool(im.registered)


def _cam_from_world(im) -> np.ndarray:
    """World-to-camera [3, 4] (pycolmap >= 3.12: a method; older: a property)."""
    t = im.cam_from_world
    return np.asarray((t() if callable(t) else t).matrix(), np.float64)


def _intrinsics(cam, where: str):
    """(w, h) -> pixel (fx, fy, cx, cy) for a pinhole-family camera without distortion."""
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    if model not in PINHOLE_MODELS:
        raise DatasetError(f"{where}: unsupported camera model {model} (supported: "
                           f"{', '.join(PINHOLE_MODELS)} without distortion); run "
                           "`colmap image_undistorter` to get a PINHOLE model")
    fx, fy = float(cam.focal_length_x), float(cam.focal_length_y)
    cx, cy = float(cam.principal_point_x), float(cam.principal_point_y)
    extra = np.asarray(cam.params)[list(cam.extra_params_idxs())]
    if extra.size and np.any(extra != 0):
        shift = _distortion_shift(cam, fx, fy, cx, cy)
        if not shift <= MAX_DISTORTION_PX:
            raise DatasetError(
                f"{where}: {model} camera with non-negligible distortion (params "
                f"{np.round(extra, 6).tolist()}, up to {shift:.2f} px at the border); run "
                "`colmap image_undistorter` and load its output (PINHOLE cameras)")
    return scaled_intrinsics(fx, fy, cx, cy, int(cam.width), int(cam.height), where)


def _distortion_shift(cam, fx, fy, cx, cy) -> float:
    """Largest pixel displacement the camera's distortion causes along the image border."""
    w, h = float(cam.width), float(cam.height)
    t = np.linspace(0.0, 1.0, 9)
    uv = np.concatenate([np.stack([t * w, 0 * t], 1), np.stack([t * w, h + 0 * t], 1),
                         np.stack([0 * t, t * h], 1), np.stack([w + 0 * t, t * h], 1)])  # [36, 2]
    xy = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(len(uv))], 1)
    try:
        proj = np.asarray(cam.img_from_cam(xy, check_cheirality=False), np.float64)
    except TypeError:
        proj = np.asarray(cam.img_from_cam(xy[:, :2]), np.float64)
    d = np.linalg.norm(proj - uv, axis=1)
    return float(d.max()) if np.all(np.isfinite(d)) else float("inf")


def _points(rec, model_dir: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
    pts = [p for _, p in sorted(rec.points3D.items(), key=lambda kv: kv[0])]  # by id
    if not pts:
        return None, None
    xyz = np.array([p.xyz for p in pts], np.float64)                    # [P, 3]
    with np.errstate(over="ignore"):
        bad = int(np.count_nonzero(~np.isfinite(xyz.astype(np.float32)).all(1)))
    if bad:
        raise DatasetError(f"{model_dir}: {bad} of {len(xyz)} 3D points have non-finite or "
                           "out-of-range coordinates (corrupt points3D file)")
    rgb = np.array([p.color for p in pts], np.float32) / 255.0          # [P, 3]
    return xyz, rgb


def _mask_paths(root: Path, masks: str | None, names: list[str]) -> dict[str, Path]:
    """Mask file per image name: ``<dir>/<name>.png`` (COLMAP) or ``<dir>/<stem>.<ext>``."""
    if masks is None:
        return {}
    mask_dir = root / masks
    if not mask_dir.is_dir():
        raise DatasetError(f"{mask_dir}: mask folder not found")
    by_stem: dict[str, Path] = {}
    for p in sorted(mask_dir.rglob("*")):
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS:
            by_stem.setdefault(p.relative_to(mask_dir).with_suffix("").as_posix(), p)
    out, missing = {}, []
    for name in names:
        p = mask_dir / f"{name}.png"
        if not p.is_file():
            p = by_stem.get(Path(name).with_suffix("").as_posix())
        if p is None:
            missing.append(name)
        else:
            out[name] = p
    if missing:
        raise missing_error("mask files", mask_dir, missing, len(names))
    return out
