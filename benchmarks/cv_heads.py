"""The shipped light head's cross-validation folds, so that the benchmarks' held-out scores
stay held out (a helper of the benchmarks, not one itself).

The shipped head (``comgs_dr/lighting/weights/light_head.pt``) is fitted on every shared real
map. For the maps the benchmarks score as held out (``pano_data.HELD_OUT``),
``data/light_head_cv/<stem>.pt`` is the head fitted the same way without that map
(``comgs train-light-head --cv-out``), each with its model card (``<stem>.json``).
"""
from __future__ import annotations

from pathlib import Path

CV_HEADS = Path(__file__).resolve().parent / "data" / "light_head_cv"


def held_out_head(stem: str, head="default"):
    """The light head to score map ``stem`` with, so that the score is a held-out one:
    ``head`` itself unless it is "default" (or None) and ``CV_HEADS/<stem>.pt`` exists, the
    shipped head's cross-validation fold that never saw that map; then that path."""
    if head not in (None, "default"):
        return head
    cv = CV_HEADS / f"{stem}.pt"
    return cv if cv.is_file() else head
