"""Similarity transforms (uniform scale · rotation + translation) for placing objects, and
the placement file of a composition (``transform.json``, compatible with ComGS/R3DG).

File format: ``{"<name>": {"transform": [16 floats, row-major object→world]}}`` or
``{"<name>": {"location": [x, y, z], "rotation": [rx, ry, rz], "scale": s}}`` with the
rotation in Euler degrees applied X, then Y, then Z (Blender's default 'XYZ' mode, world
axes: R = R_z · R_y · R_x) and a uniform scale (a number or three equal numbers). Any
number of objects. Non-uniform scales, mirrors, singular or non-finite matrices are refused
with an error that names the object.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

SCALE_TOL = 1e-4          # relative spread of the three axis scales accepted as uniform


@dataclass(frozen=True)
class Similarity:
    """x_world = scale · R · x_object + t."""
    scale: float
    rotation: np.ndarray        # [3, 3] proper rotation
    translation: np.ndarray     # [3]

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def points(self, p) -> np.ndarray:
        """[N, 3] object-space points -> world."""
        return self.scale * np.asarray(p, np.float64) @ self.rotation.T + self.translation

    def directions(self, d) -> np.ndarray:
        """[N, 3] directions (normals stay unit: a similarity preserves angles)."""
        return np.asarray(d, np.float64) @ self.rotation.T

    def inverse(self) -> "Similarity":
        rt = self.rotation.T
        return Similarity(1.0 / self.scale, rt, -(rt @ self.translation) / self.scale)


def _numbers(value, name: str, what: str) -> np.ndarray:
    """``value`` as a flat float64 array, or ValueError naming the object and the key (for
    strings, objects, ragged lists or integers beyond the float range)."""
    try:
        return np.asarray(value, np.float64).ravel()
    except (TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"placement of {name!r}: {what} must be numbers, got {value!r:.80} "
                         f"({e})") from None


def from_matrix(m, name: str = "object") -> Similarity:
    """A [4, 4] (or 16 row-major values) object→world matrix -> Similarity, or ValueError."""
    a = _numbers(m, name, "'transform'")
    if a.size != 16:
        raise ValueError(f"placement of {name!r}: 'transform' needs 16 numbers (row-major 4×4), "
                         f"got {a.size}")
    a = a.reshape(4, 4)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"placement of {name!r}: the transform has non-finite entries")
    if not np.allclose(a[3], [0, 0, 0, 1], atol=1e-6):
        raise ValueError(f"placement of {name!r}: the last row must be 0 0 0 1 (no projection), "
                         f"got {a[3].tolist()}")
    lin = a[:3, :3]
    det = np.linalg.det(lin)
    if abs(det) < 1e-12:
        raise ValueError(f"placement of {name!r}: the transform is singular (det {det:.3g})")
    if det < 0:
        raise ValueError(f"placement of {name!r}: the transform mirrors the object (det < 0); "
                         "only rotations, uniform scales and translations are supported")
    axes = np.linalg.norm(lin, axis=0)
    s = float(axes.mean())
    if np.ptp(axes) > SCALE_TOL * s:
        raise ValueError(f"placement of {name!r}: non-uniform scale {np.round(axes, 6).tolist()} "
                         "(only similarity transforms: one scale for all axes)")
    r = lin / s
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-4):
        raise ValueError(f"placement of {name!r}: the 3×3 part is sheared, not a scaled rotation")
    u, _, vt = np.linalg.svd(r)              # re-orthonormalise the rotation
    return Similarity(s, u @ vt, a[:3, 3].copy())


def euler_xyz_deg(rx: float, ry: float, rz: float) -> np.ndarray:
    """R = R_z(rz) · R_y(ry) · R_x(rx) (degrees; Blender's 'XYZ' Euler mode)."""
    x, y, z = np.radians([rx, ry, rz])
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def from_entry(name: str, entry) -> Similarity:
    """One entry of a placement file (see the module docstring)."""
    if not isinstance(entry, dict):
        raise ValueError(f"placement of {name!r}: expected an object with 'transform' or "
                         f"'location'/'rotation'/'scale', got {type(entry).__name__}")
    if "transform" in entry:
        extra = {"location", "rotation", "scale"} & set(entry)
        if extra:
            raise ValueError(f"placement of {name!r}: give 'transform' or "
                             f"location/rotation/scale, not both ({sorted(extra)})")
        return from_matrix(entry["transform"], name)
    if not {"location", "rotation", "scale"} & set(entry):
        raise ValueError(f"placement of {name!r}: no 'transform' and no location/rotation/scale")

    def vec(key, default, n=3):
        v = _numbers(entry.get(key, default), name, repr(key))
        if v.size != n or not np.all(np.isfinite(v)):
            raise ValueError(f"placement of {name!r}: {key!r} needs {n} finite numbers, got {entry.get(key)!r}")
        return v
    loc = vec("location", [0, 0, 0])
    rot = vec("rotation", [0, 0, 0])
    sc = _numbers(entry.get("scale", 1.0), name, "'scale'")
    if sc.size not in (1, 3) or not np.all(np.isfinite(sc)) or np.any(sc <= 0):
        raise ValueError(f"placement of {name!r}: 'scale' must be one positive number (or three "
                         f"equal ones), got {entry.get('scale')!r}")
    if np.ptp(sc) > SCALE_TOL * sc.mean():
        raise ValueError(f"placement of {name!r}: non-uniform scale {sc.tolist()} (only similarity "
                         "transforms: one scale for all axes)")
    return Similarity(float(sc.mean()), euler_xyz_deg(*rot), loc)


def read_placements(path) -> dict[str, Similarity]:
    """Read a ``transform.json``: {name: Similarity}, in file order."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"placement file not found: {p}")
    try:
        data = json.loads(p.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"placement file {p}: not valid UTF-8 JSON ({e})") from None
    if not isinstance(data, dict) or not data:
        raise ValueError(f"placement file {p}: expected a non-empty object {{name: placement}}")
    out = {}
    for name, entry in data.items():
        try:
            out[name] = from_entry(name, entry)
        except ValueError as e:
            raise ValueError(f"placement file {p}: {e}") from None
    return out


def write_placements(path, placements: dict) -> Path:
    """Write {name: Similarity} as row-major 'transform' entries."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps({k: {"transform": v.matrix.ravel().tolist()} for k, v in placements.items()},
                            indent=1))
    return p
