"""A run folder: ``run.json`` links a reconstruction run to its dataset."""
from __future__ import annotations

import json
from pathlib import Path

from comgs_dr.train import checkpoint as ck

RUN_FILE = "run.json"


def write_run_info(run_dir: Path, data_dir, preset: str, resolution_scale: int, white_background: bool):
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    ck.atomic_write_text(Path(run_dir) / RUN_FILE, json.dumps({
        "data": str(Path(data_dir).resolve()), "preset": preset,
        "resolution_scale": resolution_scale, "white_background": white_background}, indent=1))


def read_run_info(run_dir: Path) -> dict:
    p = Path(run_dir) / RUN_FILE
    if not p.exists():
        raise FileNotFoundError(f"{p} not found: is {run_dir} a `comgs reconstruct` run folder?")
    return json.loads(p.read_text())
