"""A run folder: ``run.json`` links a reconstruction run to its dataset."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from comgs_dr.data.load import DatasetError, camera_fingerprint, load_dataset
from comgs_dr.train.checkpoint import atomic_write_text

RUN_FILE = "run.json"


def write_run_info(run_dir: Path, data_dir, preset: str, resolution_scale: int,
                   white_background: bool) -> None:
    """``run_dir/run.json``: the dataset (and its cameras' :func:`camera_fingerprint`, so that a
    dataset changed after training is refused, not silently misplaced), preset, scale."""
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(run_dir) / RUN_FILE, json.dumps({
        "data": str(Path(data_dir).resolve()), "preset": preset,
        "resolution_scale": resolution_scale, "white_background": white_background,
        "cameras_sha256": camera_fingerprint(data_dir)}, indent=1))


_FIELDS = {"data": str, "preset": str, "resolution_scale": int, "white_background": bool}


def read_run_info(run_dir: Path) -> dict:
    """The checked contents of ``run_dir/run.json`` (ValueError naming the file when it is
    not a JSON object with ``data``, ``preset``, ``resolution_scale``, ``white_background``
    of the right types)."""
    p = Path(run_dir) / RUN_FILE
    if not p.exists():
        raise FileNotFoundError(f"{p} not found: is {run_dir} a `comgs reconstruct` run folder?")
    try:
        info = json.loads(p.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{p}: not valid UTF-8 JSON ({e}); re-run `comgs reconstruct` "
                         "or fix the file") from None
    if not isinstance(info, dict):
        raise ValueError(f"{p}: expected a JSON object, got {type(info).__name__}")
    bad = [f"{k!r} (expected {t.__name__}, got {info.get(k)!r:.60})" for k, t in _FIELDS.items()
           if type(info.get(k)) is not t]
    if bad:
        raise ValueError(f"{p}: missing or mistyped fields {', '.join(bad)}")
    if info["resolution_scale"] < 1:
        raise ValueError(f"{p}: resolution_scale must be >= 1, got {info['resolution_scale']}")
    return info


def load_run_dataset(run_dir: Path, info: dict | None = None, pixels: bool = True):
    """The dataset of a run, loaded as step 1 loaded it (background, resolution scale);
    ``pixels`` False: its cameras only (``images.load_view``)."""
    info = info or read_run_info(run_dir)
    check_run_cameras(run_dir, info)
    return load_dataset(info["data"], white_background=info["white_background"],
                        resolution_scale=info["resolution_scale"], pixels=pixels)


def check_run_cameras(run_dir: Path, info: dict) -> None:
    """DatasetError when the run's dataset's camera files changed since the run was trained
    (``run.json`` → ``cameras_sha256``; runs written before it was recorded pass)."""
    want = info.get("cameras_sha256")
    if not want or not Path(info["data"]).exists():
        return
    have = camera_fingerprint(info["data"])
    if have != want:
        raise DatasetError(
            f"{Path(run_dir) / RUN_FILE}: the cameras of its dataset {info['data']} changed "
            f"since this run was trained (a new `comgs sfm` into that folder?): the run's "
            f"surfels are in the old cameras' frame and would render misplaced. Point 'data' "
            f"at the dataset it was trained on, or re-run `comgs reconstruct`")


def select_views(views: list, max_views: int | None) -> list:
    """At most ``max_views`` views, evenly spread (all when None)."""
    if not max_views or max_views >= len(views):
        return list(views)
    return [views[int(i)] for i in np.linspace(0, len(views) - 1, max_views).round()]
