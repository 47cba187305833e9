"""Material editing of relightable surfels (the paper's editing stage: change an object's
albedo, roughness or metallic before relighting/compositing).

:func:`edit_materials` returns edited parameters for the whole object or a subset (surfel
indices, a boolean mask, or an axis-aligned box); :func:`parse_material_spec` and
:func:`parse_mask_spec` read the CLI's ``--material`` / ``--material-mask`` strings.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from comgs_dr.surfels.params import SurfelParams


@dataclass(frozen=True)
class MaterialEdit:
    """Albedo set to ``albedo`` (linear RGB) or multiplied by ``albedo_scale`` (a scalar or
    RGB), roughness and metallic set; None leaves a field as it is."""
    albedo: tuple | None = None
    albedo_scale: tuple | None = None
    roughness: float | None = None
    metallic: float | None = None

    def __post_init__(self):
        if self.albedo is not None and self.albedo_scale is not None:
            raise ValueError("material edit: give albedo=R,G,B or scale=S, not both")
        for name, v, lo, hi in (("albedo", self.albedo, 0, 1), ("scale", self.albedo_scale, 0, np.inf)):
            if v is not None:
                a = np.asarray(v, np.float64)
                if a.shape not in ((), (1,), (3,)) or not np.all(np.isfinite(a)) or (a < lo).any() or (a > hi).any():
                    raise ValueError(f"material edit: {name} must be 1 or 3 finite values in "
                                     f"[{lo}, {hi}], got {v!r}")
        for name, v in (("roughness", self.roughness), ("metallic", self.metallic)):
            if v is not None and not (np.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"material edit: {name} must be in [0, 1], got {v!r}")

    @property
    def empty(self) -> bool:
        return all(v is None for v in (self.albedo, self.albedo_scale, self.roughness, self.metallic))


_KEYS = ("albedo", "scale", "roughness", "metallic")


def parse_material_spec(spec: str) -> MaterialEdit:
    """``"albedo=0.8,0.2,0.1,roughness=0.3,metallic=1"`` or ``"scale=1.5,roughness=0.1"``."""
    spec = spec.strip()
    pat = re.compile(r"(%s)=([^=]+?)(?=,(?:%s)=|$)" % ("|".join(_KEYS), "|".join(_KEYS)))
    keys = [m.group(1) for m in pat.finditer(spec)]
    twice = sorted({k for k in keys if keys.count(k) > 1})
    if twice:
        raise ValueError(f"--material {spec!r}: {', '.join(twice)} given more than once")
    found = {m.group(1): m.group(2) for m in pat.finditer(spec)}
    rebuilt = ",".join(f"{k}={v}" for k, v in ((m.group(1), m.group(2)) for m in pat.finditer(spec)))
    if not found or rebuilt.replace(" ", "") != spec.replace(" ", ""):
        raise ValueError(f"--material {spec!r}: expected comma-separated key=value with keys "
                         f"{', '.join(_KEYS)} (albedo=R,G,B or scale=S[,S,S]; roughness=X; metallic=Y)")

    def nums(key):
        try:
            v = tuple(float(x) for x in found[key].split(","))
        except ValueError:
            raise ValueError(f"--material: {key}={found[key]!r} is not a number list") from None
        return v

    def one(key):
        v = nums(key)
        if len(v) != 1:
            raise ValueError(f"--material: {key} takes one value, got {found[key]!r}")
        return v[0]
    return MaterialEdit(albedo=nums("albedo") if "albedo" in found else None,
                        albedo_scale=nums("scale") if "scale" in found else None,
                        roughness=one("roughness") if "roughness" in found else None,
                        metallic=one("metallic") if "metallic" in found else None)


def parse_mask_spec(spec: str | None, count: int) -> np.ndarray | None:
    """``None`` (whole object), ``box:x0,y0,z0,x1,y1,z1`` (world-space box, returned as
    such for :func:`select`), or a file of surfel indices (.npy, or text: whitespace/comma
    separated). Returns indices [M] or a ('box', lo, hi) tuple."""
    if spec is None:
        return None
    if spec.startswith("box:"):
        try:
            v = np.array([float(x) for x in spec[4:].split(",")])
        except ValueError:
            raise ValueError(f"--material-mask {spec!r}: box needs 6 numbers") from None
        if v.shape != (6,) or not np.all(np.isfinite(v)) or np.any(v[:3] > v[3:]):
            raise ValueError(f"--material-mask {spec!r}: box:x0,y0,z0,x1,y1,z1 with x0 ≤ x1 ...")
        return ("box", v[:3], v[3:])
    p = Path(spec)
    if not p.is_file():
        raise FileNotFoundError(f"--material-mask: index file {p} not found")
    idx = np.load(p) if p.suffix == ".npy" else np.array(re.split(r"[\s,]+", p.read_text().strip()), float)
    idx = np.asarray(idx)
    if idx.dtype == bool:
        if idx.shape != (count,):
            raise ValueError(f"--material-mask {p}: a boolean mask needs {count} entries, got {idx.shape}")
        return np.flatnonzero(idx)
    if idx.ndim != 1 or not np.all(np.isfinite(idx)) or np.any(idx != np.round(idx)):
        raise ValueError(f"--material-mask {p}: expected a list of integer surfel indices")
    idx = idx.astype(np.int64)
    if idx.size and (idx.min() < 0 or idx.max() >= count):
        raise ValueError(f"--material-mask {p}: indices must be in [0, {count}), got "
                         f"[{idx.min()}, {idx.max()}]")
    return idx


def select(params: SurfelParams, mask) -> np.ndarray:
    """Boolean [N] selection: all (None), indices, a boolean mask or ('box', lo, hi)."""
    n = params.count
    if mask is None:
        return np.ones(n, bool)
    if isinstance(mask, tuple) and mask and mask[0] == "box":
        c = np.asarray(params.to_numpy()["means"])
        return np.all((c >= mask[1]) & (c <= mask[2]), axis=1)
    m = np.asarray(mask)
    if m.dtype == bool:
        if m.shape != (n,):
            raise ValueError(f"material mask: {m.shape} booleans for {n} surfels")
        return m
    out = np.zeros(n, bool)
    out[m.astype(np.int64)] = True
    return out


def edit_materials(params: SurfelParams, edit: MaterialEdit, mask=None) -> SurfelParams:
    """A copy of ``params`` with ``edit`` applied to the selected surfels (albedo clipped to
    [0, 1] after scaling)."""
    sel = select(params, mask)
    d = params.to_numpy()
    a = np.array(d["albedo"], np.float64)
    if edit.albedo is not None:
        a[sel] = np.broadcast_to(np.asarray(edit.albedo, np.float64), (3,))
    if edit.albedo_scale is not None:
        a[sel] = np.clip(a[sel] * np.broadcast_to(np.asarray(edit.albedo_scale, np.float64), (3,)), 0, 1)
    r = np.array(d["roughness"], np.float64)
    m = np.array(d["metallic"], np.float64)
    if edit.roughness is not None:
        r[sel] = edit.roughness
    if edit.metallic is not None:
        m[sel] = edit.metallic
    d.update(albedo=a.astype(np.float32), roughness=r.astype(np.float32), metallic=m.astype(np.float32))
    return SurfelParams.from_numpy(**d)


__all__ = ["MaterialEdit", "parse_material_spec", "parse_mask_spec", "select", "edit_materials"]
