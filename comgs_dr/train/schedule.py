"""Learning-rate schedules."""
from __future__ import annotations

import math


def log_lerp(start: float, end: float, t: float) -> float:
    """Exponential decay from ``start`` (t = 0) to ``end`` (t = 1), linear in log space:
    3DGS's position learning rate, exp((1 − t)·ln start + t·ln end)."""
    return math.exp((1 - t) * math.log(start) + t * math.log(end))
