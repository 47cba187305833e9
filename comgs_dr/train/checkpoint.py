"""Atomic checkpoints of a reconstruction run (surfels + optimiser + loop state)."""
from __future__ import annotations

import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from comgs_dr.surfels.params import (
    SurfelParams,
    field_from_numpy,
    field_names,
    field_to_numpy,
)

CKPT_NAME = "checkpoint.npz"
FORMAT = "comgs_dr.checkpoint/1"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write via a temporary file in the same folder + os.replace (never a torn file)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def save_checkpoint(run_dir: Path, params: SurfelParams, opt, keys: dict, state: dict) -> Path:
    """Surfels, Adam moments/step counts per field and a JSON-able ``state`` in one npz."""
    n = params.count
    arrays = {f"p_{k}": v for k, v in params.to_numpy().items()}
    for f, key in keys.items():
        if key in opt.state:
            _, _, _, (t, m, v, _) = opt.state[key]
            arrays[f"m_{f}"] = field_to_numpy(f, m, n)
            arrays[f"v_{f}"] = field_to_numpy(f, v, n)
            arrays[f"t_{f}"] = np.asarray(t, np.uint32)
    arrays["state"] = np.frombuffer(json.dumps({"format": FORMAT, **state}).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path = Path(run_dir) / CKPT_NAME
    atomic_write_bytes(path, buf.getvalue())
    return path


def load_checkpoint(run_dir: Path):
    """(params, moments {field: (t, m, v)} as numpy, state dict) or None if absent."""
    path = Path(run_dir) / CKPT_NAME
    if not path.exists():
        return None
    try:
        z = np.load(path)
        state = json.loads(bytes(z["state"]).decode())
    except Exception as e:  # noqa: BLE001 - any decoding failure means a bad file
        raise ValueError(f"checkpoint {path} is unreadable ({e}); delete it to start over") from e
    if state.get("format") != FORMAT:
        raise ValueError(f"checkpoint {path} has format {state.get('format')!r}, expected {FORMAT}")
    params = SurfelParams.from_numpy(**{k: z[f"p_{k}"] for k in field_names()})
    moments = {f: (z[f"t_{f}"], z[f"m_{f}"], z[f"v_{f}"]) for f in field_names() if f"m_{f}" in z}
    return params, moments, state


def restore_moments(opt, keys: dict, params: SurfelParams, moments: dict) -> None:
    """Put saved Adam moments back into ``opt`` (after its parameters were registered)."""
    for f, (t, m, v) in moments.items():
        key = keys.get(f)
        if key is None or key not in opt.state:
            continue
        value, promoted, lr, (t0, _, _, vmax) = opt.state[key]
        like = getattr(params, f)
        opt.state[key] = (value, promoted, lr, (type(t0)(t), field_from_numpy(f, m, like),
                                                 field_from_numpy(f, v, like), vmax))
