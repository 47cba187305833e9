"""OpenEXR files through the ``OpenEXR.File`` API: named channels and layers, half or float
pixels, string header attributes, atomic writes and clear errors.

Layers follow the ``layer.channel`` naming Blender, Nuke and tev read: the unnamed layer is
``R,G,B,A`` (or ``Y``), ``depth`` is ``depth.Z``, ``normal`` is ``normal.X/Y/Z`` and other
layers are named by their channel count (``albedo.R/G/B``, ``roughness.Y``).

Every write goes to a temporary file in the destination folder and is moved into place with
``os.replace``, so a reader never sees a half-written EXR. Unreadable files (missing, empty,
not an EXR, truncated, corrupt) raise FileNotFoundError / ValueError naming the file and the
problem. Values are stored as given (NaN/Inf included): callers validate what they need.

Colour images are returned in linear Rec. 709 / sRGB primaries, the package's working space:
an RGB file whose ``chromaticities`` attribute names other primaries (or XYZ) is converted
with colour-science's RGB-to-RGB matrix, without chromatic adaptation, as ``mi.Bitmap`` did
(colour-science is imported only for such files).
"""
from __future__ import annotations

import io
import os
import secrets
from pathlib import Path

import numpy as np
import OpenEXR

__all__ = ["MAGIC", "channel_names", "write_exr", "read_exr", "read_attrs", "write_image",
           "read_image", "write_layers", "read_layers"]

MAGIC = b"\x76\x2f\x31\x01"                 # the first four bytes of every OpenEXR file
HALF_MAX = float(np.finfo(np.float16).max)  # 65504
_PIXEL = {"float": np.float32, "half": np.float16}
_BY_LAYER = {"depth": ("Z",), "normal": ("X", "Y", "Z"), "position": ("X", "Y", "Z")}
_BY_COUNT = {1: ("Y",), 2: ("Y", "A"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
_RANK = {"R": 0, "G": 1, "B": 2, "X": 3, "Y": 4, "Z": 5, "A": 6}   # canonical channel order
REC709 = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)   # x,y of R, G, B, white
_RESERVED = {"channels", "compression", "dataWindow", "displayWindow", "lineOrder",
             "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth", "type", "name",
             "tiles", "chunkCount", "version"}


def channel_names(layer: str, count: int) -> tuple[str, ...]:
    """Full channel names of a ``count``-channel layer: ('depth', 1) -> ('depth.Z',)."""
    names = _BY_LAYER.get(layer) if layer in _BY_LAYER else _BY_COUNT.get(count)
    if names is None or len(names) != count:
        raise ValueError(f"EXR layer {layer or '<root>'!r}: cannot name {count} channels "
                         f"(expected {len(names) if names else '1-4'})")
    return tuple(f"{layer}.{c}" if layer else c for c in names)


def _sorted_names(names) -> list[str]:
    """Channel names in canonical order within their layer (R,G,B,A / X,Y,Z), then by name."""
    def key(n):
        layer, _, c = n.rpartition(".")
        return layer, _RANK.get(c, len(_RANK)), c
    return sorted(names, key=key)


# ---------------------------------------------------------------------------------------
# Writing

def write_exr(path, channels: dict, attrs: dict | None = None,
              pixel_type: str = "float") -> Path:
    """Write {full channel name: [H, W] array} as a ZIP-compressed scanline EXR, atomically.

    ``attrs``: string header attributes (e.g. {'layout': 'octahedral'}); ``pixel_type``:
    'float' (32-bit) or 'half' (16-bit; finite values beyond ±65504 raise ValueError
    rather than silently becoming Inf).
    """
    p = Path(path)
    if pixel_type not in _PIXEL:
        raise ValueError(f"{p}: pixel_type must be 'float' or 'half', got {pixel_type!r}")
    if not isinstance(channels, dict):
        raise TypeError(f"{p}: write_exr takes {{channel name: [H, W] array}}; for an "
                        "[H, W, C] image use write_image")
    if not channels:
        raise ValueError(f"{p}: no channels to write")
    shape, chans = None, {}
    for name, a in channels.items():
        a = np.asarray(a)
        if not name or a.ndim != 2 or 0 in a.shape:
            raise ValueError(f"{p}: channel {name!r} must be a named non-empty [H, W] array, "
                             f"got shape {a.shape}")
        if shape is not None and a.shape != shape:
            raise ValueError(f"{p}: channel {name!r} is {a.shape}, the others {shape}")
        shape = a.shape
        a = a.astype(np.float64 if pixel_type == "half" else np.float32, copy=False)
        if pixel_type == "half":
            fin = np.abs(a[np.isfinite(a)])
            if fin.size and fin.max() > HALF_MAX:
                raise ValueError(f"{p}: channel {name!r} holds {fin.max():.4g}, beyond the "
                                 f"half-float range ±{HALF_MAX:g} (write pixel_type='float')")
        chans[name] = np.ascontiguousarray(a, _PIXEL[pixel_type])
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (attrs or {}).items():
        if k in _RESERVED or not isinstance(v, str):
            raise ValueError(f"{p}: header attribute {k!r} must be a non-reserved name with "
                             f"a string value, got {type(v).__name__}")
        header[k] = v
    buf = io.BytesIO()
    OpenEXR.File(header, chans).write(buf)
    _atomic_write(p, buf.getvalue())
    return p


def _atomic_write(p: Path, data: bytes) -> None:
    """Bytes to ``p`` via a uniquely named temporary file beside it + os.replace."""
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f"{p.name}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "xb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_image(path, img, attrs: dict | None = None, pixel_type: str = "float") -> Path:
    """[H, W] or [H, W, C] image: C = 1 -> Y, 2 -> Y,A, 3 -> R,G,B, 4 -> R,G,B,A."""
    return write_layers(path, {"": img}, attrs, pixel_type)


def write_layers(path, layers: dict, attrs: dict | None = None,
                 pixel_type: str = "float") -> Path:
    """Multi-layer EXR from {layer: [H, W] or [H, W, C]}, e.g. {'': rgba, 'depth': z,
    'normal': xyz, 'albedo': rgb, 'roughness': y} -> R,G,B,A, depth.Z, normal.X/Y/Z,
    albedo.R/G/B, roughness.Y (:func:`channel_names`)."""
    chans = {}
    for layer, a in layers.items():
        a = np.asarray(a)
        a = a[..., None] if a.ndim == 2 else a
        if a.ndim != 3:
            raise ValueError(f"{path}: layer {layer or '<root>'!r} must be [H, W] or "
                             f"[H, W, C], got shape {a.shape}")
        for k, name in enumerate(channel_names(layer, a.shape[2])):
            chans[name] = a[..., k]
    return write_exr(path, chans, attrs, pixel_type)


# ---------------------------------------------------------------------------------------
# Reading

def _open(path, header_only: bool = False):
    """``OpenEXR.File`` of ``path``; FileNotFoundError / ValueError naming file and problem."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"EXR file not found: {p}")
    with open(p, "rb") as f:
        head = f.read(4)
    if not head:
        raise ValueError(f"{p}: empty file (0 bytes), not an EXR image")
    if head != MAGIC:
        raise ValueError(f"{p}: not an OpenEXR file (starts with {head!r}, not the EXR "
                         "magic number 76 2f 31 01)")
    try:
        f = OpenEXR.File(str(p), separate_channels=True, header_only=header_only)
        parts = f.parts
        if not parts:
            raise ValueError("no image part")
        if not header_only:
            for part in parts:
                if any(c.pixels is None for c in part.channels.values()):
                    raise ValueError("missing pixel data")
    except (RuntimeError, ValueError, TypeError) as e:
        raise ValueError(f"{p}: truncated or corrupt EXR file ({e})") from None
    return f


def read_exr(path) -> tuple[dict, dict]:
    """({full channel name: [H, W] array (float16/float32/uint32 as stored)},
    {string header attribute: value}); the channels of all parts of a multi-part file."""
    chans, header = _read(path)
    return chans, _attrs(header)


def _read(path) -> tuple[dict, dict]:
    """(channels of all parts, first part's full header)."""
    f = _open(path)
    chans = {}
    for part in f.parts:
        for name, c in part.channels.items():
            a = np.asarray(c.pixels)
            if chans and a.shape != next(iter(chans.values())).shape:
                raise ValueError(f"{path}: parts of different sizes are not supported")
            chans[name] = a
    return chans, f.parts[0].header


def _attrs(header: dict) -> dict:
    return {k: v for k, v in header.items() if isinstance(v, str) and k != "name"}


def read_attrs(path) -> dict:
    """String header attributes of ``path`` (header only, no pixels read)."""
    return _attrs(_open(path, header_only=True).parts[0].header)


def read_layers(path) -> dict:
    """{layer: float32 [H, W, C]} with channels in canonical order (R,G,B,A / X,Y,Z);
    the unnamed layer is ''."""
    chans, _ = read_exr(path)
    layers: dict = {}
    for name in _sorted_names(chans):
        layers.setdefault(name.rpartition(".")[0], []).append(chans[name])
    return {k: np.stack(v, -1).astype(np.float32) for k, v in layers.items()}


def _to_rec709(rgb: np.ndarray, chroma) -> np.ndarray:
    """[..., 3] RGB in the primaries/white ``chroma`` (8 floats) -> linear Rec. 709."""
    import colour  # lazy: ~1 s to import, needed only for files in other primaries

    c = np.asarray(chroma, np.float64)
    src = colour.RGB_Colourspace("EXR file", c[:6].reshape(3, 2), c[6:])
    dst = colour.RGB_Colourspace("Rec. 709", np.reshape(REC709[:6], (3, 2)), REC709[6:])
    m = colour.matrix_RGB_to_RGB(src, dst, chromatic_adaptation_transform=None)   # [3, 3]
    return (rgb.astype(np.float64) @ m.T).astype(rgb.dtype)


def read_image(path) -> np.ndarray:
    """float32 [H, W, C] of the unnamed layer in any channel order: R,G,B(,A) (C = 3/4) or
    Y(,A) (C = 1/2). A file whose only layer is named (``Image.R`` …) is read as well.
    RGB in other primaries than Rec. 709 (``chromaticities``) is converted to Rec. 709."""
    chans, header = _read(path)
    root = {n for n in chans if "." not in n}
    layers = {n.rpartition(".")[0] for n in chans if "." in n}
    prefix = ""
    if not root and len(layers) == 1:
        prefix = layers.pop() + "."
        root = {n[len(prefix):] for n in chans}
    for want in (("R", "G", "B", "A"), ("R", "G", "B"), ("Y", "A"), ("Y",)):
        if set(want) <= root:
            img = np.stack([chans[prefix + c] for c in want], -1).astype(np.float32)
            chroma = header.get("chromaticities")
            if (len(want) >= 3 and chroma is not None
                    and not np.allclose(chroma, REC709, rtol=0, atol=1e-4)):
                img[..., :3] = _to_rec709(img[..., :3], chroma)
            return img
    raise ValueError(f"{path}: no RGB, RGBA or Y image in the file (channels: "
                     f"{', '.join(_sorted_names(chans))})")
