"""ProbeSet: Surface Octahedral Probes (positions, normals, octahedral textures), save/load.

Paper, "Illumination Modeling": each SOP stores an indirect-radiance texture L_in and an
occlusion texture O (16² octahedral texels in sec. 4.1). Both live in one 4-channel
atlas (RGB = linear indirect radiance, A = occlusion ∈ [0, 1]) so one vector gather per
bilinear tap fetches both. In memory the atlas carries the 1-texel octahedral wrap border
(``core.octahedral``); files hold the interior only.

File format (``.npz``): ``positions`` [P,3] f32, ``normals`` [P,3] f32, ``texture``
[P,R,R,4] f32 (interior), ``radius`` (query radius), ``meta`` (JSON string: version,
colour space, how the probes were made).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np

from comgs_dr.core import octahedral as octa
from comgs_dr.core.hostarray import to_jit

FORMAT_VERSION = 1
CHANNELS = 4


@dataclass
class ProbeSet:
    positions: np.ndarray            # [P, 3]
    normals: np.ndarray              # [P, 3] unit, the surface normal the probe was offset along
    res: int                         # R, texels per tile side
    radius: float                    # fixed query radius of the FRNN search (eq. knn)
    texture: np.ndarray | None = None    # [P, R, R, 4] interior texels; None = not baked
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.positions = np.ascontiguousarray(self.positions, np.float32).reshape(-1, 3)
        self.normals = np.ascontiguousarray(self.normals, np.float32).reshape(-1, 3)
        p = len(self.positions)
        if p == 0:
            raise ValueError("ProbeSet: no probe positions")
        if len(self.normals) != p:
            raise ValueError(f"ProbeSet: {p} positions but {len(self.normals)} normals")
        if not (np.isfinite(self.positions).all() and np.isfinite(self.normals).all()):
            raise ValueError("ProbeSet: positions/normals hold NaN or Inf")
        if not (self.res >= 2 and np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"ProbeSet: need res ≥ 2 and radius > 0, got {self.res}, "
                             f"{self.radius}")
        if self.texture is not None:
            self.texture = np.ascontiguousarray(self.texture, np.float32)
            want = (p, self.res, self.res, CHANNELS)
            if self.texture.shape != want:
                raise ValueError(f"ProbeSet: texture shape {self.texture.shape}, expected {want}")
            if not np.isfinite(self.texture).all():
                raise ValueError("ProbeSet: texture holds NaN or Inf")

    @property
    def count(self) -> int:
        return len(self.positions)

    # Dr.Jit views ---------------------------------------------------------------------
    def bordered(self) -> np.ndarray:
        """[P, R+2, R+2, 4] atlas with the wrap border."""
        if self.texture is None:
            raise ValueError("ProbeSet: textures are not baked yet (see sops.bake)")
        return octa.add_border_np(self.texture)

    def atlas(self):
        """Flat bordered ``mi.Float`` atlas (the optimised parameter in step 2)."""
        return to_jit(mi.Float, self.bordered().ravel())

    def set_from_atlas(self, atlas) -> None:
        """Copy an optimised bordered atlas back into ``texture``."""
        b = np.asarray(atlas, np.float32).reshape(self.count, self.res + 2, self.res + 2,
                                                   CHANNELS)
        self.texture = np.ascontiguousarray(octa.strip_border_np(b))

    # files ----------------------------------------------------------------------------
    def save(self, path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        meta = dict(self.meta, version=FORMAT_VERSION, channels="rgb indirect (linear), occlusion")
        tmp = p.with_name(p.name + ".tmp.npz")
        np.savez_compressed(tmp, positions=self.positions, normals=self.normals,
                            texture=(self.texture if self.texture is not None
                                     else np.zeros((0,), np.float32)),
                            res=np.int64(self.res), radius=np.float64(self.radius),
                            meta=np.array(json.dumps(meta)))
        tmp.replace(p)
        return p

    @classmethod
    def load(cls, path) -> "ProbeSet":
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"probe file not found: {p}")
        try:
            with open(p, "rb") as f, np.load(f, allow_pickle=False) as z:   # closed on errors
                meta = json.loads(str(z["meta"]))
                if not isinstance(meta, dict):
                    raise ValueError(f"'meta' is not a JSON object: {meta!r:.40}")
                version = meta.get("version", 0)
                if not isinstance(version, int) or version > FORMAT_VERSION:
                    raise ValueError(f"format version {version!r:.20}, this comgs_dr reads "
                                     f"≤ {FORMAT_VERSION}")
                tex = z["texture"]
                res, radius = z["res"], z["radius"]
                if res.shape != () or radius.shape != ():
                    raise ValueError(f"'res' and 'radius' must be scalars, got shapes "
                                     f"{res.shape}, {radius.shape}")
                return cls(positions=z["positions"], normals=z["normals"], res=int(res),
                           radius=float(radius), texture=tex if tex.size else None,
                           meta=meta)
        except (ValueError, TypeError) as e:
            if "pickle" in str(e):          # numpy's hint to load it unsafely is not repeated
                raise ValueError(f"bad probe file {p}: it holds pickled Python objects, not a "
                                 f"probe file written by comgs_dr (not loaded: unpickling can "
                                 f"run code)") from None
            raise ValueError(f"bad probe file {p}: {e}") from None
        except Exception as e:  # noqa: BLE001 - zip/npy decoding raises many types on damage
            raise ValueError(f"cannot read probe file {p}: {type(e).__name__}: {e}") from None
