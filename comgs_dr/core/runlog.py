"""One (wall time, metric) log format for every stage: ``metrics.jsonl`` (JSON lines).

Each line is one record ``{"stage": str, "time_s": float, ...}``: ``time_s`` is the stage's
wall time in seconds when the record was taken (training time for the training loops,
evaluation excluded), the other keys are numbers (``iteration``, ``loss``, ``psnr_test``,
``si_rmse``, ...) or short strings (``part``, ``frame``). Writers append one line per record
and flush, so a killed run leaves every complete line readable; :func:`read_records` skips a
torn last line. :func:`rewrite` replaces the whole file atomically (a resumed run rewrites
its records from its checkpointed log). ``comgs report`` plots every numeric key against
``time_s`` (``comgs_dr.eval.report``).

Why hand-written: a log of a few hundred lines needs no logging framework; JSON lines is the
format every plotting tool and ``pandas.read_json(lines=True)`` reads.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

LOG_NAME = "metrics.jsonl"


def _clean(rec: dict) -> dict:
    """JSON-safe copy: numpy scalars to Python, non-finite floats to None (JSON has no NaN)."""
    out = {}
    for k, v in rec.items():
        if getattr(v, "ndim", 0) != 0:
            continue                              # arrays are not logged
        v = json_safe(v)
        if isinstance(v, (int, float, str, bool)) or v is None:
            out[str(k)] = v
    return out


def json_safe(x):
    """``x`` for ``json.dumps(..., allow_nan=False)``: dict keys as strings, tuples as lists,
    numpy arrays and scalars as Python lists and numbers (``tolist``), non-finite floats as
    None (JSON has no NaN / Infinity; Python writes them, strict parsers reject them)."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, (str, bytes)):
        return json_safe(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def record(stage: str, time_s: float, **values) -> dict:
    """One record (``values`` that are not scalars are dropped: the log holds scalars)."""
    return _clean({"stage": str(stage), "time_s": round(float(time_s), 4), **values})


def append(folder, rec: dict, name: str = LOG_NAME) -> None:
    """Append one record as one line of ``folder/metrics.jsonl`` (flushed)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / name, "a", encoding="utf-8") as f:
        f.write(json.dumps(_clean(rec)) + "\n")
        f.flush()


def rewrite(folder, records, name: str = LOG_NAME) -> Path:
    """Replace ``folder/metrics.jsonl`` by ``records`` (atomic: temp file + rename)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{name}.")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        for r in records:
            f.write(json.dumps(_clean(r)) + "\n")
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)              # mkstemp makes 0600: keep the usual mode
    os.replace(tmp, folder / name)
    return folder / name


def from_train_log(stage: str, log: list) -> list[dict]:
    """Records of a training loop's log (``{"iteration", "time_s", **stats}``)."""
    return [record(stage, r.get("time_s", 0.0), **{k: v for k, v in r.items() if k != "time_s"})
            for r in log]


def part_records(stage: str, timings: dict, **extra) -> list[dict]:
    """One record per timed part ({part: seconds}, in order; a ``total`` entry is skipped):
    ``time_s`` = the cumulative time at the part's end, ``part``, ``part_s`` and ``extra``."""
    t, out = 0.0, []
    for part, sec in timings.items():
        if part != "total":
            t += float(sec)
            out.append(record(stage, t, part=part, part_s=float(sec), **extra))
    return out


def read_records(path) -> list[dict]:
    """The records of a ``metrics.jsonl`` file (a torn or unparsable line is skipped; a
    record without ``stage``/``time_s`` raises ValueError naming the file and line)."""
    path = Path(path)
    out = []
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            continue                      # a line torn by a killed writer
        if not isinstance(r, dict) or "stage" not in r or "time_s" not in r:
            raise ValueError(f"{path}:{i}: not a metrics record (needs 'stage' and 'time_s')")
        out.append(r)
    return out
