"""Reading ``torch.save`` files: with ``weights_only=True`` (tensors and plain containers
only, so a foreign file cannot run code), and one error that names the file and what is
wrong with it."""
from __future__ import annotations

import re

import torch


def torch_load_error(exc: Exception) -> str:
    """Why ``torch.load(weights_only=True)`` refused a file, in one line: its own message goes
    on to advise ``weights_only=False``, which would run any code a foreign file holds."""
    text = str(exc).strip()
    m = re.search(r"WeightsUnpickler error:\s*(.+?)\s*(?:\n\n|$)", text, re.S)
    reason = " ".join((m.group(1) if m else (text.splitlines() or [""])[0]).split())
    reason = reason.split(". ")[0]             # its first sentence: the advice comes after
    return f"{type(exc).__name__}: {reason}"


def load_torch_file(path, expected_format: str | None, what: str, map_location="cpu",
                    error: type[Exception] = ValueError, hint: str = ""):
    """What ``torch.save`` wrote to ``path``, loaded with ``weights_only=True``.

    ``what`` names the kind of file in the messages; ``error`` is the exception raised and
    ``hint`` is appended to its message (e.g. "; delete it to start over"):

    * ``<path>: not a readable <what> (<reason>)`` when torch cannot load it;
    * ``<path>: not a <what> (format <expected_format> expected)`` when ``expected_format``
      is given and the file is not a dict whose ``"format"`` is that string.
    """
    try:
        obj = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any decoding failure means a bad file
        raise error(f"{path}: not a readable {what} ({torch_load_error(exc)}){hint}") from exc
    if expected_format is not None and (not isinstance(obj, dict)
                                        or obj.get("format") != expected_format):
        raise error(f"{path}: not a {what} (format {expected_format!r} expected){hint}")
    return obj
