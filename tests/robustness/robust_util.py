"""Shared helpers of the robustness suite: hypothesis profile, byte mutations, the error
contract and a watchdog (not a conftest: ``from conftest import ...`` must keep meaning
tests/conftest.py)."""
from __future__ import annotations

import contextlib
import io
import json
import signal
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from PIL import Image

# Reproducible in CI: no example database, derandomised; bigger counts only under -m slow.
settings.register_profile(
    "robustness", database=None, derandomize=True, deadline=None, print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                           HealthCheck.function_scoped_fixture])
BASE = settings.get_profile("robustness")


def slow(test):
    """Bigger example counts: marked ``slow`` and run only when selected (``-m slow``), so
    the default run of the suite stays short."""
    skip = pytest.mark.skipif("'slow' not in (config.getoption('markexpr') or '')",
                              reason="bigger example counts: run with -m slow")
    return pytest.mark.slow(skip(test))


def fuzz(max_examples: int, deadline_ms: float | None = 10_000):
    """Explicit per-test settings on top of the reproducible profile.

    ``deadline_ms`` is generous: two other test runs share the 2 cores; the watchdog
    (:func:`time_limit`) is what turns a real hang into a failure."""
    return settings(BASE, max_examples=max_examples, deadline=deadline_ms)


# Errors a parser may raise for bad input; anything else (IndexError, KeyError,
# struct.error, TypeError, AttributeError, UnicodeDecodeError as such, ...) is a bug.
CLEAR_ERRORS = (ValueError, FileNotFoundError, IsADirectoryError, PermissionError)


def check_clear_error(exc: BaseException, *names) -> None:
    """``exc`` is a clear error: an accepted type whose message names one of ``names``
    (the file or folder) and says more than the name."""
    assert isinstance(exc, CLEAR_ERRORS), f"{type(exc).__name__}: {exc}"
    assert not isinstance(exc, UnicodeDecodeError), f"raw UnicodeDecodeError: {exc}"
    msg = str(exc)
    assert any(str(n) in msg for n in names), f"message does not name {names}: {msg!r}"
    rest = msg
    for n in names:
        rest = rest.replace(str(n), "")
    assert len(rest.strip(" :()'\"")) >= 8, f"message says nothing beyond the path: {msg!r}"


@contextlib.contextmanager
def time_limit(seconds: int):
    """Fail (TimeoutError) if the block runs longer than ``seconds`` (SIGALRM; main thread)."""
    def _raise(signum, frame):
        raise TimeoutError(f"hang: still running after {seconds} s")
    old = signal.signal(signal.SIGALRM, _raise)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


@contextlib.contextmanager
def scratch():
    """A fresh temporary folder per hypothesis example (tmp_path is per test)."""
    with tempfile.TemporaryDirectory(prefix="comgs_robust_") as d:
        yield Path(d)


# --------------------------------------------------------------------- byte mutations
def truncate(data: bytes, frac: float) -> bytes:
    return data[: int(len(data) * frac)]


def flip(data: bytes, positions: list[int], values: list[int]) -> bytes:
    b = bytearray(data)
    for p, v in zip(positions, values):
        if b:
            b[p % len(b)] = v
    return bytes(b)


@st.composite
def mutated_bytes(draw, data: bytes, header_len: int | None = None):
    """``data`` truncated, with flipped bytes (optionally inside the first ``header_len``
    bytes), replaced by random bytes, or emptied."""
    kind = draw(st.sampled_from(["truncate", "flip", "flip_header", "random", "empty",
                                 "append"]))
    if kind == "truncate":
        return truncate(data, draw(st.floats(0.0, 0.999)))
    if kind in ("flip", "flip_header"):
        hi = (header_len or len(data)) if kind == "flip_header" else len(data)
        k = draw(st.integers(1, 8))
        pos = draw(st.lists(st.integers(0, max(hi - 1, 0)), min_size=k, max_size=k))
        val = draw(st.lists(st.integers(0, 255), min_size=k, max_size=k))
        return flip(data, pos, val)
    if kind == "random":
        return draw(st.binary(min_size=1, max_size=256))
    if kind == "append":
        return data + draw(st.binary(min_size=1, max_size=64))
    return b""


# --------------------------------------------------------------------- JSON mutations
JSON_SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-10**30, 10**30),
                         st.floats(allow_nan=True, allow_infinity=True),
                         st.text(max_size=8))
JSON_ANY = st.recursive(JSON_SCALARS, lambda c: st.one_of(
    st.lists(c, max_size=4), st.dictionaries(st.text(max_size=6), c, max_size=4)),
    max_leaves=12)


@st.composite
def mutated_json(draw, doc):
    """A JSON document derived from ``doc``: a key dropped, a value replaced by one of a
    wrong type (or NaN/Inf/huge), an extra key, a list emptied, or the whole document
    replaced (a list, a scalar)."""
    paths = list(_paths(doc))
    kind = draw(st.sampled_from(["drop", "retype", "extra", "empty_list", "whole"]))
    doc = json.loads(json.dumps(doc))
    if kind == "whole":
        return draw(JSON_ANY)
    if kind == "extra":
        dicts = [p for p in paths if isinstance(_get(doc, p), dict)] or [()]
        tgt = _get(doc, draw(st.sampled_from(dicts)))
        if isinstance(tgt, dict):
            tgt[draw(st.text(min_size=1, max_size=8))] = draw(JSON_ANY)
        return doc
    if kind == "empty_list":
        lists = [p for p in paths if isinstance(_get(doc, p), list)]
        if lists:
            _set(doc, draw(st.sampled_from(lists)), [])
        return doc
    inner = [p for p in paths if p]
    if not inner:
        return draw(JSON_ANY)
    p = draw(st.sampled_from(inner))
    if kind == "drop":
        parent = _get(doc, p[:-1])
        del parent[p[-1]]
        return doc
    _set(doc, p, draw(JSON_ANY))
    return doc


def _paths(doc, prefix=()):
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, prefix + (i,))


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def _set(doc, path, value):
    _get(doc, path[:-1])[path[-1]] = value


def dump_json(doc) -> bytes:
    """JSON text as Python writes it (NaN/Infinity literals allowed, as other tools do)."""
    return json.dumps(doc, allow_nan=True).encode()


@st.composite
def corrupted_json_bytes(draw, doc):
    """Bytes of a mutated version of ``doc``: structural mutations, byte damage, or
    non-UTF-8 text."""
    kind = draw(st.sampled_from(["json", "json", "bytes", "latin1"]))
    if kind == "json":
        return dump_json(draw(mutated_json(doc)))
    raw = dump_json(doc)
    if kind == "bytes":
        return draw(mutated_bytes(raw))
    return raw[:-1] + b' "\xff\xfe\xe9" ' + raw[-1:]


def listing(folder) -> set[str]:
    return {str(p.relative_to(folder)) for p in Path(folder).rglob("*")}


def write(path, data: bytes) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


# --------------------------------------------------------------------- tiny datasets
W, H = 8, 6


def png_bytes(seed=0, alpha=False) -> bytes:
    """A random W x H RGB(A) PNG."""
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 256, (H, W, 4 if alpha else 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


def nerf_doc(split: str, n: int = 2) -> dict:
    """transforms_<split>.json: n cameras 4 units above the origin, looking down."""
    frames = []
    for i in range(n):
        m = np.eye(4)
        m[:3, 3] = (0.3 * i, 0.0, 4.0)
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": m.tolist()})
    return {"camera_angle_x": 0.8, "frames": frames}


def nerf_folder(root, docs: dict | None = None, images: dict | None = None):
    """A NeRF-synthetic folder with 2 train + 1 test RGBA views of W x H."""
    docs = docs or {}
    for split, n in (("train", 2), ("test", 1)):
        raw = docs.get(split, json.dumps(nerf_doc(split, n)).encode())
        write(root / f"transforms_{split}.json", raw)
        for i in range(n):
            name = f"{split}/r_{i}.png"
            write(root / name, (images or {}).get(name, png_bytes(i, alpha=True)))
    return root
