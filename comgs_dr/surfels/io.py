"""Surfel files: PLY import/export (ours, 2DGS, 3DGS, ComGS, GS-IR, IRGS, R3DG) and ``.splat``.

Written layout (binary little-endian, one ``vertex`` element, all float32)::

    x y z nx ny nz f_dc_0..2 f_rest_0..f_rest_{3(K-1)-1} opacity scale_0 scale_1
    rot_0..3 albedo_0..2 roughness metallic
    comment comgs_dr format=1
    comment comgs_dr color_space=srgb

3DGS conventions: rot_0 = w, log-scales, opacity logit, ``f_rest`` channel-major
(R coefficients 1..K-1, then G, then B). ``nx ny nz`` is the surfel normal (third
column of R(q)), written for viewers and ignored on read. Materials are stored
activated (linear albedo, roughness, metallic in [0, 1]) in files carrying the
``comgs_dr`` tag. Files without the tag come from other codes, which all store
materials *pre-activation*; the activation of the code whose names match is
applied on import (see ``_MATERIAL_CONVENTIONS``).
"""
from __future__ import annotations

import dataclasses
import logging
import os

import numpy as np
import plyfile

from comgs_dr.surfels.params import SurfelParams, sh_from_base_colour

log = logging.getLogger(__name__)

FORMAT_TAG = "comgs_dr"
FORMAT_VERSION = "1"
COLOR_SPACES = ("srgb", "linear")
MATERIAL_DEFAULTS = {"albedo": 0.5, "roughness": 0.5, "metallic": 0.0}
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3")
_F_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}   # 3*((d+1)^2-1) -> degree d
_QUAT_EPS2 = 1e-24                             # |q|^2 below this is "zero" (as in kernel.quat_frame)


class SurfelFileError(ValueError):
    """A surfel file that cannot be loaded; the message names the file and the property."""


@dataclasses.dataclass
class SurfelFileInfo:
    """What ``load_ply(..., return_meta=True)`` / ``load_splat`` found in a file."""
    path: str
    layout: str                     # "comgs_dr", "2dgs" (2 scales), "3dgs" (3 scales), "splat"
    n_scales: int                   # scales in the file (3 -> flattened to a surfel)
    sh_degree: int
    color_space: str                # recorded space, or "srgb" assumed for untagged files
    color_space_recorded: bool
    materials: str                  # convention used to decode materials (see _MATERIAL_CONVENTIONS)
    defaulted: tuple = ()           # material fields filled with MATERIAL_DEFAULTS
    comments: tuple = ()


# --------------------------------------------------------------------- numpy quaternion helpers
def quat_to_matrix(q) -> np.ndarray:
    """[N, 4] w-first quaternions (any length > 0) -> [N, 3, 3] rotations, columns (t_u, t_v, n)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product a ⊗ b of w-first quaternions ([N, 4] or [4], broadcast)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], -1)


# Right-multiplying R(q) by a cyclic axis permutation P: columns (a0,a1,a2) -> (a_{k+1}, a_{k+2}, a_k).
_CYCLIC_QUAT = {0: np.array([0.5, 0.5, 0.5, 0.5]),     # 120° about (1,1,1): x->y, y->z, z->x
                1: np.array([0.5, -0.5, -0.5, -0.5]),  # 240° about (1,1,1): x->z, y->x, z->y
                2: np.array([1.0, 0.0, 0.0, 0.0])}


def flatten_gaussians(quats, log_scales3) -> tuple[np.ndarray, np.ndarray]:
    """3D Gaussians -> surfels: ([N,4] w-first quats, [N,3] log-scales) -> ([N,4], [N,2]).

    The surfel plane is spanned by the two largest axes; the smallest axis a_k
    becomes the normal. The frame is cycled, (t_u, t_v, n) = (a_{k+1}, a_{k+2}, a_k)
    (indices mod 3), which is a proper rotation (right-handed) and keeps the normal
    exactly equal to the smallest axis: q' = q ⊗ q_P. Scales become
    (s_{k+1}, s_{k+2}); the thickness s_k is dropped (exact only for flat Gaussians).
    """
    quats = np.asarray(quats, np.float64)                      # [N, 4]
    ls = np.asarray(log_scales3, np.float32)                   # [N, 3]
    k = np.argmin(ls, axis=1)                                  # [N] smallest axis
    q_out = quats.copy()
    for kk in (0, 1):                                          # k == 2 keeps q as is
        m = k == kk
        q_out[m] = quat_multiply(quats[m], _CYCLIC_QUAT[kk])
    rows = np.arange(len(ls))
    ls2 = np.stack([ls[rows, (k + 1) % 3], ls[rows, (k + 2) % 3]], 1)   # [N, 2]
    return q_out.astype(np.float32), ls2


# --------------------------------------------------------------------- materials of other codes
def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.clip(np.asarray(x, np.float64), -60, 60)))


# name -> {field: (ply property names, activation)}; every code below stores raw
# pre-activation values in its PLY.
_MATERIAL_CONVENTIONS = {
    # NJU-3DV/ComGS scene/gaussian_model.py: albedo_0..2, metallic, roughness, all torch.sigmoid.
    # lzhnb/GS-IR scene/gaussian_model.py: albedo_0..2, roughness, metallic, material_activation = sigmoid.
    "comgs/gs-ir": {"albedo": (("albedo_0", "albedo_1", "albedo_2"), _sigmoid),
                    "roughness": (("roughness",), _sigmoid),
                    "metallic": (("metallic",), _sigmoid)},
    # IRGS (fudan-zvg/IRGS, read from the fork piotrmwojcik/IRGS scene/gaussian_model.py):
    # base_color_0..2 -> sigmoid(x)*0.77+0.03, roughness -> sigmoid, metallic -> sigmoid.
    "irgs": {"albedo": (("base_color_0", "base_color_1", "base_color_2"),
                        lambda x: _sigmoid(x) * 0.77 + 0.03),
             "roughness": (("roughness",), _sigmoid),
             "metallic": (("metallic",), _sigmoid)},
    # R3DG (NJU-3DV/Relightable3DGaussian scene/gaussian_model.py): base_color_0..2 ->
    # sigmoid(x)*0.77+0.03, roughness -> sigmoid(x)*0.9+0.09; no metallic.
    "r3dg": {"albedo": (("base_color_0", "base_color_1", "base_color_2"),
                        lambda x: _sigmoid(x) * 0.77 + 0.03),
             "roughness": (("roughness",), lambda x: _sigmoid(x) * 0.9 + 0.09),
             "metallic": (("metallic",), _sigmoid)},
}


def _material_convention(names: set, tagged: bool, encoding: str) -> tuple[str, dict]:
    """(name, {field: (properties, activation or None)}) for a file's material properties."""
    if "base_color_0" in names:
        name = "irgs" if "metallic" in names else "r3dg"
    else:
        name = "comgs/gs-ir"
    conv = _MATERIAL_CONVENTIONS[name]
    if encoding == "activated" or (encoding == "auto" and tagged):   # values already in [0, 1]
        return ("comgs_dr" if tagged else "activated"), {k: (v[0], None) for k, v in conv.items()}
    return name, conv


# --------------------------------------------------------------------- reading
def _read_plydata(path: str):
    try:
        with open(path, "rb") as f:
            return plyfile.PlyData.read(f, mmap=False)
    except (FileNotFoundError, IsADirectoryError, PermissionError):
        raise
    except Exception as e:  # plyfile raises PlyParseError, ValueError, EOFError, ... on bad data
        raise SurfelFileError(f"{path}: not a readable PLY file or truncated data "
                              f"({type(e).__name__}: {e})") from e


def _parse_comments(comments) -> dict:
    meta = {}
    for c in comments:
        parts = str(c).split()
        if parts and parts[0] == FORMAT_TAG:
            for kv in parts[1:]:
                if "=" in kv:
                    k, v = kv.split("=", 1)
                    meta[k] = v
    return meta


def load_ply(path, *, return_meta: bool = False, material_encoding: str = "auto"):
    """Load surfels from a PLY file (ours, 2DGS, 3DGS and the relightable-GS layouts).

    - 2 scales (2DGS, ComGS, IRGS, ours): taken as is.
    - 3 scales (3DGS, R3DG, GS-IR): flattened by :func:`flatten_gaussians` — the
      plane of the two largest axes becomes the surfel, the smallest axis its
      normal (right-handed frame, cyclic re-ordering of R(q)'s columns).
    - Materials: ``albedo_*``/``roughness``/``metallic`` (ComGS, GS-IR, ours) or
      ``base_color_*`` (IRGS with ``metallic``, R3DG without). Untagged files are
      decoded with their code's activation; ``material_encoding="activated"``
      forces values to be read as already in [0, 1], ``"raw"`` forces decoding.
      Missing fields get MATERIAL_DEFAULTS, are listed in ``SurfelFileInfo.defaulted``
      and logged as a warning.
    - ``f_rest`` must hold 0, 9, 24 or 45 values (SH degree 0..3).

    Returns SurfelParams, or (SurfelParams, SurfelFileInfo) with ``return_meta``.
    Raises SurfelFileError for anything that is not a complete, finite surfel file.
    """
    if material_encoding not in ("auto", "raw", "activated"):
        raise ValueError(f"load_ply: material_encoding must be 'auto', 'raw' or 'activated', "
                         f"got {material_encoding!r}")
    path = os.fspath(path)
    ply = _read_plydata(path)
    names_el = [e.name for e in ply.elements]
    if "vertex" not in names_el:
        raise SurfelFileError(f"{path}: no 'vertex' element (elements: {names_el or 'none'})")
    el = ply["vertex"]
    names = [p.name for p in el.properties]
    nset = set(names)
    n = int(el.count)
    missing = [p for p in _REQUIRED if p not in nset]
    if missing:
        raise SurfelFileError(f"{path}: missing required vertex properties {missing}")
    if n == 0:
        raise SurfelFileError(f"{path}: the 'vertex' element has zero vertices")

    # --- SH layout
    rest = sorted((p for p in names if p.startswith("f_rest_")),
                  key=lambda s: int(s[7:]) if s[7:].isdigit() else -1)
    if len(rest) not in _F_REST_COUNTS or rest != [f"f_rest_{i}" for i in range(len(rest))]:
        raise SurfelFileError(
            f"{path}: inconsistent 'f_rest_*' properties ({len(rest)} found); expected "
            "f_rest_0..f_rest_{M-1} with M = 3*((d+1)^2-1) in {0, 9, 24, 45} for SH degree d = 0..3")
    degree = _F_REST_COUNTS[len(rest)]
    K = (degree + 1) ** 2
    n_scales = 3 if "scale_2" in nset else 2
    scale_names = [f"scale_{i}" for i in range(n_scales)]
    if f"scale_{n_scales}" in nset:
        raise SurfelFileError(f"{path}: properties 'scale_0..scale_{n_scales}' found; a surfel file "
                              "has 2 (2DGS) or 3 (3DGS) scales")

    # --- materials
    comments = tuple(str(c) for c in ply.comments)
    tag = _parse_comments(comments)
    tagged = "format" in tag
    conv_name, conv = _material_convention(nset, tagged, material_encoding)
    mat_props, defaulted = {}, []
    for field, (props, _) in conv.items():
        present = [p for p in props if p in nset]
        if not present:
            defaulted.append(field)
        elif len(present) != len(props):
            raise SurfelFileError(f"{path}: incomplete material '{field}': missing properties "
                                  f"{[p for p in props if p not in nset]}")
        else:
            mat_props[field] = props

    # --- gather + validate (finite values)
    used = list(_REQUIRED) + scale_names[2:] + rest + [p for ps in mat_props.values() for p in ps]
    cols = {}
    bad = []
    for p in used:
        try:
            with np.errstate(over="ignore"):                     # |x| > 3.4e38 -> inf, reported below
                a = np.asarray(el[p]).astype(np.float32)        # [N]
        except (ValueError, TypeError) as e:
            raise SurfelFileError(f"{path}: property '{p}' is not numeric ({e})") from e
        nbad = int(np.count_nonzero(~np.isfinite(a)))
        if nbad:
            bad.append(f"'{p}' ({nbad} of {n} rows)")
        cols[p] = a
    if bad:
        raise SurfelFileError(f"{path}: non-finite values (NaN/Inf, or beyond float32's "
                              f"±3.4e38) in properties {', '.join(bad)}")

    def stack(ps):
        return np.stack([cols[p] for p in ps], 1)

    quats = stack(["rot_0", "rot_1", "rot_2", "rot_3"])        # [N, 4] w-first
    nq = int(np.count_nonzero(np.sum(quats.astype(np.float64) ** 2, 1) < _QUAT_EPS2))
    if nq:
        raise SurfelFileError(f"{path}: zero-length quaternion in properties 'rot_0..rot_3' "
                              f"({nq} of {n} rows)")
    log_scales = stack(scale_names)                            # [N, 2|3]
    if n_scales == 3:
        quats, log_scales = flatten_gaussians(quats, log_scales)
    sh = np.empty((n, K, 3), np.float32)                       # [N, K, 3]
    sh[:, 0, :] = stack(["f_dc_0", "f_dc_1", "f_dc_2"])
    if K > 1:   # channel-major: [N, 3, K-1] -> [N, K-1, 3]
        sh[:, 1:, :] = stack(rest).reshape(n, 3, K - 1).transpose(0, 2, 1)

    mats = {}
    for field, props in mat_props.items():
        act = conv[field][1]
        v = stack(props) if len(props) > 1 else cols[props[0]]
        mats[field] = v if act is None else act(v).astype(np.float32)
    if defaulted:
        log.warning("%s: no %s in the file; using defaults %s", path, ", ".join(defaulted),
                    {k: MATERIAL_DEFAULTS[k] for k in defaulted})

    params = SurfelParams.from_numpy(
        means=stack(["x", "y", "z"]), quats=quats, log_scales=log_scales,
        opacity_logit=cols["opacity"], sh=sh, albedo=mats.get("albedo"),
        roughness=mats.get("roughness"), metallic=mats.get("metallic"))
    if not return_meta:
        return params
    cs = tag.get("color_space")
    info = SurfelFileInfo(
        path=path, layout="comgs_dr" if tagged else ("3dgs" if n_scales == 3 else "2dgs"),
        n_scales=n_scales, sh_degree=degree, color_space=cs or "srgb",
        color_space_recorded=cs is not None,
        materials=conv_name if mat_props else "none", defaulted=tuple(defaulted), comments=comments)
    return params, info


# --------------------------------------------------------------------- writing
def save_ply(params: SurfelParams, path, *, color_space: str = "srgb") -> None:
    """Write surfels in our PLY layout (see module docstring); reloads bit-exactly.

    ``color_space`` is the space of the SH colour ("srgb" for fits of sRGB photos and
    3DGS-family data, "linear" otherwise); it is recorded in a PLY comment.
    Refuses (ValueError) non-finite parameters or zero quaternions, which
    :func:`load_ply` would reject.
    """
    if color_space not in COLOR_SPACES:
        raise ValueError(f"save_ply: color_space must be one of {COLOR_SPACES}, got {color_space!r}")
    path = os.fspath(path)
    d = params.to_numpy()
    n = d["means"].shape[0]
    if n == 0:
        raise ValueError("save_ply: no surfels to write")
    for k, v in d.items():
        nbad = int(np.count_nonzero(~np.isfinite(v).reshape(n, -1).all(1)))
        if nbad:
            raise ValueError(f"save_ply({path}): '{k}' has NaN/Inf in {nbad} of {n} surfels")
    q = d["quats"]                                             # [N, 4]
    nq = int(np.count_nonzero(np.sum(q.astype(np.float64) ** 2, 1) < _QUAT_EPS2))
    if nq:
        raise ValueError(f"save_ply({path}): 'quats' has {nq} zero-length quaternion(s)")
    K = d["sh"].shape[1]
    normal = quat_to_matrix(q)[:, :, 2].astype(np.float32)     # [N, 3]
    f_rest = d["sh"][:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (K - 1))   # [N, 3(K-1)] channel-major
    columns = ([("x", d["means"][:, 0]), ("y", d["means"][:, 1]), ("z", d["means"][:, 2]),
                ("nx", normal[:, 0]), ("ny", normal[:, 1]), ("nz", normal[:, 2])]
               + [(f"f_dc_{i}", d["sh"][:, 0, i]) for i in range(3)]
               + [(f"f_rest_{i}", f_rest[:, i]) for i in range(f_rest.shape[1])]
               + [("opacity", d["opacity_logit"]), ("scale_0", d["log_scales"][:, 0]),
                  ("scale_1", d["log_scales"][:, 1])]
               + [(f"rot_{i}", q[:, i]) for i in range(4)]
               + [(f"albedo_{i}", d["albedo"][:, i]) for i in range(3)]
               + [("roughness", d["roughness"]), ("metallic", d["metallic"])])
    arr = np.empty(n, dtype=[(name, "<f4") for name, _ in columns])
    for name, v in columns:
        arr[name] = v
    el = plyfile.PlyElement.describe(arr, "vertex")
    comments = [f"{FORMAT_TAG} format={FORMAT_VERSION}", f"{FORMAT_TAG} color_space={color_space}",
                f"{FORMAT_TAG} materials=activated (albedo linear, roughness, metallic in [0,1])"]
    _atomic_write(path, plyfile.PlyData([el], text=False, byte_order="<", comments=comments).write)


def _atomic_write(path: str, write) -> None:
    """``write(tmp)`` next to ``path``, then rename: a failed write (disk full, interrupt)
    leaves any previous file intact and no partial file behind."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"save_ply({path}): folder {folder} does not exist")
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


# --------------------------------------------------------------------- .splat
_SPLAT_DTYPE = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def load_splat(path, *, return_meta: bool = False):
    """Load an antimatter15 ``.splat`` file (32 bytes per splat) as surfels.

    Per splat: position 3×f32, *linear* scale 3×f32, RGBA 4×u8, rotation 4×u8 as
    (q/|q|)·128+128, w-first. Decoded as the viewer shows it: colour c = byte/255 →
    SH DC (c − 0.5)/C0 (degree 0, sRGB); α = byte/255 clipped to
    [0.5/255, 1 − 0.5/255] → logit; q = (byte − 128)/128; the 3 scales are
    flattened as in :func:`flatten_gaussians`. Materials are defaulted.
    """
    path = os.fspath(path)
    with open(path, "rb") as f:
        raw = f.read()
    if len(raw) == 0 or len(raw) % _SPLAT_DTYPE.itemsize:
        raise SurfelFileError(f"{path}: size {len(raw)} bytes is not a positive multiple of "
                              f"{_SPLAT_DTYPE.itemsize} (not a .splat file, or truncated)")
    a = np.frombuffer(raw, dtype=_SPLAT_DTYPE)
    n = len(a)
    bad = [f"'{k}' ({int(np.count_nonzero(~np.isfinite(a[k]).all(1)))} of {n} rows)"
           for k in ("pos", "scale") if not np.isfinite(a[k]).all()]
    if bad:
        raise SurfelFileError(f"{path}: non-finite values (NaN/Inf) in {', '.join(bad)}")
    nneg = int(np.count_nonzero((a["scale"] <= 0).any(1)))
    if nneg:
        raise SurfelFileError(f"{path}: non-positive 'scale' in {nneg} of {n} rows")
    q = (a["rot"].astype(np.float64) - 128.0) / 128.0         # [N, 4]
    nq = int(np.count_nonzero(np.sum(q * q, 1) < _QUAT_EPS2))
    if nq:
        raise SurfelFileError(f"{path}: zero-length quaternion in 'rot' ({nq} of {n} rows)")
    quats, log_scales = flatten_gaussians(q, np.log(a["scale"].astype(np.float64)))
    rgba = a["rgba"].astype(np.float64) / 255.0               # [N, 4]
    alpha = np.clip(rgba[:, 3], 0.5 / 255, 1 - 0.5 / 255)
    sh = sh_from_base_colour(rgba[:, :3])                     # [N, 1, 3]
    log.warning("%s: .splat files carry no materials; using defaults %s", path, MATERIAL_DEFAULTS)
    params = SurfelParams.from_numpy(means=a["pos"], quats=quats, log_scales=log_scales,
                                     opacity_logit=np.log(alpha / (1 - alpha)), sh=sh)
    if not return_meta:
        return params
    return params, SurfelFileInfo(path=path, layout="splat", n_scales=3, sh_degree=0,
                                  color_space="srgb", color_space_recorded=False, materials="none",
                                  defaulted=tuple(MATERIAL_DEFAULTS))
