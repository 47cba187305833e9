"""Image/mask reading, alpha compositing, area downscaling and View assembly.

Downscaling by an integer ``resolution_scale`` k crops the right/bottom edges to a
multiple of k and averages k x k blocks (area averaging, what PIL's BOX filter does at an
integer factor, but in float32 so nothing is re-quantised). Pixel intrinsics (top-left
corner origin) are then simply divided by k: the crop does not move the principal point,
and image, mask and camera stay exactly consistent.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image, UnidentifiedImageError

from comgs_dr.data.types import Camera, DatasetError, View

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
_HIGH_BIT = ("I;16", "I;16B", "I;16L", "I;16N", "I")


def _open(path: Path, pixels: bool = True):
    """The PIL image of ``path``, decoded (``pixels``) or its header only (size, mode), or a
    DatasetError naming the file."""
    try:
        with open(path, "rb") as f:     # closed even when decoding fails
            im = Image.open(f)
            if pixels:
                im.load()
            return im
    except FileNotFoundError:
        raise DatasetError(f"{path}: image file not found") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise DatasetError(f"{path}: unreadable or corrupt image ({e})") from None


def image_size(path) -> tuple[int, int]:
    """(width, height) of an image file from its header (no pixels decoded)."""
    return _open(Path(path), pixels=False).size


def read_image(path) -> np.ndarray:
    """[H, W, 3 or 4] float32 in [0, 1]; 4 channels when the file has alpha."""
    im = _open(Path(path))
    if im.mode in _HIGH_BIT:                           # 16-bit grayscale
        g = np.asarray(im, np.float32) / 65535.0
        return np.repeat(np.clip(g, 0, 1)[..., None], 3, -1)
    if im.mode == "F":
        return np.repeat(np.clip(np.asarray(im, np.float32), 0, 1)[..., None], 3, -1)
    alpha = "A" in im.getbands() or "transparency" in im.info
    return np.asarray(im.convert("RGBA" if alpha else "RGB"), np.float32) / 255.0


def read_mask(path) -> np.ndarray:
    """[H, W] float32 in [0, 1]: the alpha channel when it is not all opaque, else the
    luminance (0/255 masks become 0/1)."""
    im = _open(Path(path))
    if im.mode in _HIGH_BIT:
        return np.clip(np.asarray(im, np.float32) / 65535.0, 0, 1)
    if im.mode == "F":
        return np.clip(np.asarray(im, np.float32), 0, 1)
    if "A" in im.getbands() or "transparency" in im.info:
        a = np.asarray(im.convert("RGBA"), np.float32)[..., 3] / 255.0
        if a.min() < 1.0:
            return a
    return np.asarray(im.convert("L"), np.float32) / 255.0


def composite(rgba: np.ndarray, background) -> tuple[np.ndarray, np.ndarray]:
    """Straight-alpha RGBA [H, W, 4] over a background colour [3]: (rgb [H, W, 3], alpha [H, W])."""
    a = rgba[..., 3]                                   # [H, W]
    bg = np.asarray(background, np.float32)
    return rgba[..., :3] * a[..., None] + bg * (1.0 - a[..., None]), a


def downscale(arr: np.ndarray, k: int) -> np.ndarray:
    """Area-average [H, W, ...] by an integer factor k (right/bottom crop to a multiple)."""
    if k == 1:
        return arr
    h, w = arr.shape[0] // k, arr.shape[1] // k
    a = arr[: h * k, : w * k]
    return a.reshape(h, k, w, k, *arr.shape[2:]).mean(axis=(1, 3), dtype=np.float64) \
        .astype(np.float32)


def check_scale(resolution_scale) -> int:
    k = int(resolution_scale)
    if k != resolution_scale or k < 1:
        raise ValueError(f"resolution_scale must be a positive integer (1/2/4/8), "
                         f"got {resolution_scale!r}")
    return k


def resolve_image(root: Path, rel: str) -> Path | None:
    """``root/rel`` if it is a file, else ``root/rel`` + a known image extension."""
    p = root / rel
    if p.is_file():
        return p
    for ext in IMAGE_EXTENSIONS + tuple(e.upper() for e in IMAGE_EXTENSIONS):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    return None


def missing_error(what: str, where, missing: list[str], total: int) -> DatasetError:
    shown = ", ".join(missing[:5]) + (", ..." if len(missing) > 5 else "")
    return DatasetError(f"{where}: {len(missing)} of {total} {what} missing: {shown}")


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, sorted by name."""
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                  and not p.name.startswith("."))


Intrinsics = Callable[[int, int], tuple[float, float, float, float]]


def scaled_intrinsics(fx, fy, cx, cy, ref_w, ref_h, where: str) -> Intrinsics:
    """Intrinsics given for a (ref_w, ref_h) image, rescaled to the actual image size."""
    if not (np.isfinite([ref_w, ref_h]).all() and ref_w > 0 and ref_h > 0):
        raise DatasetError(f"{where}: calibrated image size {ref_w}x{ref_h} is not positive")

    def at(w: int, h: int):
        sx, sy = w / ref_w, h / ref_h
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise DatasetError(f"{where}: image is {w}x{h} but the camera is calibrated for "
                               f"{ref_w}x{ref_h} (different aspect ratio)")
        return fx * sx, fy * sy, cx * sx, cy * sy
    return at


def load_view(name: str, path: Path, to_world: np.ndarray, intrinsics: Intrinsics, k: int,
              background=None, mask_path: Path | None = None, pixels: bool = True) -> View:
    """Read one view: composite alpha onto ``background`` (mask = alpha), or read
    ``mask_path``; downscale by ``k``; intrinsics(w, h) are pixel fx, fy, cx, cy at the
    file's resolution. ``pixels`` False: the camera only; the file's header gives its size
    and ``image`` is a read-only zero-stride array of zeros of the view's shape (no memory;
    what needs the cameras of a 4K capture does not decode gigabytes), ``mask`` None."""
    img = read_image(path) if pixels else None         # [H, W, 3|4]
    w0, h0 = image_size(path) if img is None else (img.shape[1], img.shape[0])
    mask = None
    if img is not None and img.shape[2] == 4:
        img, mask = composite(img, background if background is not None else (0.0, 0.0, 0.0))
    if img is not None and mask_path is not None:
        mask = read_mask(mask_path)                    # [H, W]
        if mask.shape != (h0, w0):
            raise DatasetError(f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]} but its "
                               f"image {path} is {w0}x{h0}")
    if w0 < k or h0 < k:
        raise DatasetError(f"{path}: image {w0}x{h0} is smaller than resolution_scale {k}")
    fx, fy, cx, cy = intrinsics(w0, h0)
    cam = Camera.from_intrinsics(to_world, w0 // k, h0 // k, fx / k, fy / k, cx / k, cy / k,
                                 where=str(path))
    if img is None:
        blank = np.broadcast_to(np.zeros((), np.float32), (h0 // k, w0 // k, 3))
        return View(name=name, camera=cam, image=blank, mask=None, path=str(path))
    img = downscale(np.ascontiguousarray(img, np.float32), k)
    mask = None if mask is None else downscale(mask.astype(np.float32), k)
    return View(name=name, camera=cam, image=np.clip(img, 0.0, 1.0), mask=mask, path=str(path))


def to_u8(img) -> np.ndarray:
    """8-bit image of display values in [0, 1] (clipped; NaN -> 0; rounded)."""
    return (np.clip(np.nan_to_num(np.asarray(img, np.float64)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png8(path, img) -> None:
    """Save a display-space [H, W, 3|4] (or [H, W]) image in [0, 1] as an 8-bit PNG."""
    Image.fromarray(to_u8(img)).save(str(path))
