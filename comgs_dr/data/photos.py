"""Photos and videos as structure-from-motion input: list, orient, downsize, sample, sharpness.

A phone photo stores its pixels as the sensor saw them and an EXIF ``Orientation`` tag that
says how to turn them for display; SfM, the loaders (``data.images.read_image``) and the
renderer see raw pixels, so :func:`prepare_photo` applies the tag (PIL
``ImageOps.exif_transpose``), limits the long side and writes an upright RGB copy that keeps
the rest of the EXIF block (COLMAP reads the focal length prior from it). A video is sampled
to frames with ffmpeg (``imageio-ffmpeg``, which applies the rotation phones record); of every
``group`` consecutive candidates the sharpest is kept (:func:`sharpness`: the variance of the
Laplacian, high for crisp edges, low for motion blur), so frames stay evenly spread.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from comgs_dr.data.images import IMAGE_EXTENSIONS

VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
#: JPEG quality of re-encoded photos and frames (visually lossless; SIFT sees no blocks).
JPEG_QUALITY = 95
#: Long side (pixels) of the grey copy the sharpness is measured on: the same scale for
#: every frame of a video, and fast.
SHARPNESS_SIDE = 640
_EXIF_ORIENTATION = 0x0112


@dataclass
class PreparedImage:
    """One prepared image: ``name`` in the output folder, its source and what was done."""
    name: str
    source: str
    width: int
    height: int
    source_size: tuple[int, int]      # stored (width, height) before orientation and resizing
    rotated: bool = False             # an EXIF orientation other than "upright" was applied
    resized: bool = False
    sharpness: float | None = None    # video frames: variance of the Laplacian


def list_images(folder) -> tuple[list[Path], list[Path]]:
    """(image files, other files) directly in ``folder``, sorted by name; hidden files
    (``.DS_Store``, ``._IMG_1.jpg``) are ignored."""
    images, other = [], []
    for p in sorted(Path(folder).iterdir()):
        if p.name.startswith(".") or not p.is_file():
            continue
        (images if p.suffix.lower() in IMAGE_EXTENSIONS else other).append(p)
    return images, other


def is_video(path) -> bool:
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS


def fit_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """(w, h) scaled so the long side is at most ``max_size`` (0: unchanged), aspect kept."""
    long_side = max(width, height)
    if max_size <= 0 or long_side <= max_size:
        return width, height
    s = max_size / long_side
    return max(1, round(width * s)), max(1, round(height * s))


def open_upright(path) -> tuple[Image.Image, Image.Exif, tuple[int, int], bool, str]:
    """(8-bit RGB image turned by its EXIF orientation, its EXIF without the orientation,
    stored size, whether it was turned, stored format and mode). Raises ValueError naming
    the file when it cannot be decoded."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            stored, kind = im.size, f"{im.format}/{im.mode}"
            turned = im.getexif().get(_EXIF_ORIENTATION, 1) not in (0, 1)
            up = ImageOps.exif_transpose(im)
            exif = up.getexif()
            rgb = _rgb8(up)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError,
            Image.DecompressionBombError) as e:
        raise ValueError(f"{path}: unreadable image ({e})") from None
    exif.pop(_EXIF_ORIENTATION, None)
    return rgb, exif, stored, turned, kind


def _rgb8(im: Image.Image) -> Image.Image:
    """8-bit RGB of any PIL mode (16-bit grey scaled, not clipped; alpha dropped)."""
    if im.mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        g = np.clip(np.asarray(im, np.float32) / 257.0, 0, 255).astype(np.uint8)
        return Image.fromarray(g).convert("RGB")
    return im.convert("RGB") if im.mode != "RGB" else im.copy()


def prepare_photo(src, dst, max_size: int) -> PreparedImage:
    """``src`` upright, RGB, long side <= ``max_size`` at ``dst`` (JPEG or PNG by its
    suffix) with its EXIF less the orientation; an upright RGB JPEG/PNG photo that needs no
    resizing is copied byte for byte (no second JPEG compression)."""
    im, exif, stored, turned, kind = open_upright(src)
    size = fit_size(*im.size, max_size)
    resized = size != im.size
    same = {".jpg": "JPEG/RGB", ".jpeg": "JPEG/RGB", ".png": "PNG/RGB"}.get(
        Path(dst).suffix.lower())
    if not (turned or resized) and kind == same:
        shutil.copyfile(src, dst)
    else:
        if resized:
            im = im.resize(size, Image.LANCZOS)
        save_image(im, dst, exif)
    return PreparedImage(Path(dst).name, str(src), im.width, im.height, stored, turned, resized)


def save_image(im: Image.Image, dst, exif=None) -> None:
    dst = Path(dst)
    kw = {"exif": exif.tobytes()} if exif is not None and len(exif) else {}
    if dst.suffix.lower() in (".jpg", ".jpeg"):
        im.save(dst, quality=JPEG_QUALITY, subsampling=0, **kw)
    else:
        im.save(dst, **kw)


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image (uint8 [H, W, 3] or [H, W]),
    measured at a long side of ``SHARPNESS_SIDE``: higher is sharper."""
    im = Image.fromarray(np.asarray(rgb, np.uint8)).convert("L")
    if max(im.size) > SHARPNESS_SIDE:
        im = im.resize(fit_size(*im.size, SHARPNESS_SIDE), Image.BILINEAR)
    g = np.asarray(im, np.float32)
    if min(g.shape) < 3:
        return 0.0
    lap = (g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:] - 4.0 * g[1:-1, 1:-1])
    return float(lap.var())


def video_info(path) -> dict:
    """{"size": (w, h) of the (rotated) frames, "fps", "duration" (s), "frames" (estimate)}."""
    import imageio_ffmpeg  # optional: only videos need it
    gen = imageio_ffmpeg.read_frames(str(path))
    try:
        meta = next(gen)
    finally:
        gen.close()
    fps, duration = float(meta.get("fps") or 0), float(meta.get("duration") or 0)
    if not (fps > 0 and duration > 0):
        n, duration = imageio_ffmpeg.count_frames_and_secs(str(path))
        fps = n / duration if duration > 0 else 0.0
    return {"size": tuple(meta["size"]), "fps": fps, "duration": duration,
            "frames": int(round(fps * duration))}


def sample_rate(info: dict, fps: float, frames: int, group: int) -> float:
    """Candidate frames per second: ``group`` per kept frame, kept frames at ``fps`` or
    ``frames`` evenly over the video (``frames`` > 0 wins), never above the video's rate."""
    if frames > 0:
        if info["duration"] <= 0:
            raise ValueError("the video's duration is unknown: give --fps instead of --frames")
        rate = frames * group / info["duration"]
    else:
        rate = fps * group
    return min(rate, info["fps"]) if info["fps"] > 0 else rate


def read_video_frames(path, rate: float) -> Iterator[np.ndarray]:
    """uint8 [H, W, 3] frames of ``path`` at ``rate`` frames per second (ffmpeg's ``fps``
    filter), upright (ffmpeg applies the recorded rotation)."""
    import imageio_ffmpeg  # optional: only videos need it
    gen = imageio_ffmpeg.read_frames(str(path), output_params=["-vf", f"fps={rate:.6f}"])
    try:
        meta = next(gen)
        w, h = meta["size"]
        for buf in gen:
            yield np.frombuffer(buf, np.uint8).reshape(h, w, 3)
    finally:
        gen.close()


def sharpest_per_group(scores: list[float], group: int) -> list[int]:
    """Index of the sharpest candidate in each run of ``group`` consecutive ones."""
    g = max(1, int(group))
    return [i + int(np.argmax(scores[i:i + g])) for i in range(0, len(scores), g)]


def blurry(scores: list[float], min_ratio: float) -> list[int]:
    """Indices whose sharpness is below ``min_ratio`` x the median of ``scores``."""
    if not scores or min_ratio <= 0:
        return []
    med = float(np.median(scores))
    return [i for i, s in enumerate(scores) if s < min_ratio * med]


def frame_name(index: int, total: int) -> str:
    return f"frame_{index:0{max(5, len(str(total)))}d}.jpg"
