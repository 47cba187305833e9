"""Atomic checkpoints: parameter arrays, Adam state (``mi.ad.Adam``) and loop state in one npz.

One format for every trainer: ``p_<name>`` the parameters, ``m_/v_/t_<name>`` the Adam
moments and step counts of the optimised ones, ``state`` a JSON document carrying
``format`` (checked on load), the iteration, the log and the config. Files are written
through a temporary file and ``os.replace``, so an interrupted run never leaves a torn file:
a write that fails (full disk, unwritable folder) raises an ``OSError`` naming the file and
keeps the previous checkpoint; the temporary files a SIGKILL leaves behind are removed when
the checkpoint is next loaded.
"""
from __future__ import annotations

import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from comgs_dr.core.hostarray import to_jit

CKPT_NAME = "checkpoint.npz"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write via a temporary file in the same folder + os.replace (never a torn file)."""
    path = Path(path)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        _drop(tmp)
        kept = " (the previous version is kept)" if path.exists() else ""
        raise OSError(e.errno, f"cannot write {path}: {e.strerror or e}{kept}") from e
    except BaseException:
        _drop(tmp)
        raise


def _drop(tmp) -> None:
    if tmp is not None and os.path.exists(tmp):
        os.unlink(tmp)


def remove_stale_temporaries(path: Path) -> int:
    """Delete ``<path>.*.tmp`` files (what a killed atomic write leaves); returns how many."""
    path = Path(path)
    stale = list(path.parent.glob(path.name + ".*.tmp")) if path.parent.is_dir() else []
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def _plain(name, value) -> np.ndarray:
    return np.asarray(value)


def save_checkpoint(path: Path, fmt: str, arrays: dict, opt, keys: dict, state: dict,
                    to_numpy=_plain) -> Path:
    """Write ``arrays`` {name: ndarray}, the Adam state of ``keys`` {name: optimiser key}
    (moments converted by ``to_numpy(name, value)``) and the JSON-able ``state``."""
    out = {f"p_{k}": v for k, v in arrays.items()}
    for name, key in keys.items():
        if key in opt.state:
            _, _, _, (t, m, v, _) = opt.state[key]
            out[f"m_{name}"] = to_numpy(name, m)
            out[f"v_{name}"] = to_numpy(name, v)
            out[f"t_{name}"] = np.asarray(t, np.uint32)
    out["state"] = np.frombuffer(json.dumps({"format": fmt, **state}).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **out)
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def load_checkpoint(path: Path, fmt: str):
    """(arrays {name: ndarray}, moments {name: (t, m, v)}, state) or None if ``path`` is absent.
    ValueError (naming the file) if it is unreadable or of another format."""
    path = Path(path)
    remove_stale_temporaries(path)
    if not path.exists():
        return None
    try:
        with np.load(path) as z:
            state = json.loads(bytes(z["state"]).decode())
            files = {k: z[k] for k in z.files if k != "state"}
    except Exception as e:  # noqa: BLE001 - any decoding failure means a bad file
        raise ValueError(f"checkpoint {path} is unreadable ({e}); delete it to start over") from e
    if not isinstance(state, dict):
        raise ValueError(f"checkpoint {path}: its state is a JSON {type(state).__name__}, not an "
                         "object; delete it to start over")
    if state.get("format") != fmt:
        raise ValueError(f"checkpoint {path} has format {state.get('format')!r}, expected {fmt}")
    arrays = {k[2:]: v for k, v in files.items() if k.startswith("p_")}
    moments = {}
    for k, v in files.items():
        if k.startswith("m_"):
            name = k[2:]
            if f"t_{name}" not in files or f"v_{name}" not in files:
                raise ValueError(f"checkpoint {path}: the Adam state of {name!r} is incomplete "
                                 "(m_ without t_/v_); delete it to start over")
            moments[name] = (files[f"t_{name}"], v, files[f"v_{name}"])
    return arrays, moments, state


def restore_moments(opt, keys: dict, moments: dict, from_numpy) -> None:
    """Put saved Adam moments back into ``opt`` (after its parameters were registered);
    ``from_numpy(name, array, like)`` converts to the parameter's Dr.Jit type."""
    for name, (t, m, v) in moments.items():
        key = keys.get(name)
        if key is None or key not in opt.state:
            continue
        value, promoted, lr, (t0, m0, _, vmax) = opt.state[key]
        like = opt[key] if m0 is None else m0       # Adam keeps a tensor's moments flat
        opt.state[key] = (value, promoted, lr, (to_jit(type(t0), t), from_numpy(name, m, like),
                                                 from_numpy(name, v, like), vmax))
