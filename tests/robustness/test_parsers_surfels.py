"""Surfel files (PLY in every supported layout, ``.splat``) on random and corrupted input.

Contract: ``load_ply``/``load_splat`` return finite parameters or raise a clear error
(SurfelFileError / FileNotFoundError ...) whose message names the file; no hang;
``save_ply`` leaves no partial file behind when it fails.
"""
import functools
import io
import re

import numpy as np
import plyfile
import pytest
from hypothesis import given
from hypothesis import strategies as st
from robust_util import (
    check_clear_error,
    fuzz,
    mutated_bytes,
    scratch,
    slow,
    time_limit,
    write,
)

from comgs_dr.surfels import SurfelParams, load_ply, load_splat, save_ply
from comgs_dr.surfels.io import SurfelFileError

N = 5           # surfels per generated file: keeps every example well under a millisecond


# --------------------------------------------------------------------- valid files
def _columns(layout: str, n: int = N, seed: int = 0) -> dict:
    """name -> [n] values of a file in ``layout`` (2dgs, 3dgs, comgs, r3dg, irgs)."""
    rng = np.random.default_rng(seed)
    deg = {"2dgs": 0, "3dgs": 3, "comgs": 1, "r3dg": 1, "irgs": 0}[layout]
    cols = {k: rng.normal(size=n) for k in ("x", "y", "z", "nx", "ny", "nz")}
    cols.update({f"f_dc_{i}": rng.normal(size=n) for i in range(3)})
    cols.update({f"f_rest_{i}": rng.normal(size=n) for i in range(3 * ((deg + 1) ** 2 - 1))})
    cols["opacity"] = rng.normal(size=n)
    n_scales = 3 if layout in ("3dgs", "r3dg") else 2
    cols.update({f"scale_{i}": rng.normal(-4, 1, n) for i in range(n_scales)})
    cols.update({f"rot_{i}": rng.normal(size=n) for i in range(4)})
    if layout == "comgs":
        cols.update({f"albedo_{i}": rng.normal(size=n) for i in range(3)})
        cols.update(roughness=rng.normal(size=n), metallic=rng.normal(size=n))
    if layout in ("r3dg", "irgs"):
        cols.update({f"base_color_{i}": rng.normal(size=n) for i in range(3)})
        cols["roughness"] = rng.normal(size=n)
        if layout == "irgs":
            cols["metallic"] = rng.normal(size=n)
    return cols


def _ply_bytes(cols: dict, dtypes: dict | None = None, text=False, byte_order="<",
               comments=()) -> bytes:
    dtypes = dtypes or {}
    n = len(next(iter(cols.values())))
    arr = np.empty(n, dtype=[(k, dtypes.get(k, "f4")) for k in cols])
    for k, v in cols.items():
        arr[k] = v
    el = plyfile.PlyElement.describe(arr, "vertex")
    buf = io.BytesIO()
    plyfile.PlyData([el], text=text, byte_order=byte_order, comments=list(comments)).write(buf)
    return buf.getvalue()


def _ours_bytes() -> bytes:
    from conftest import random_surfels
    with scratch() as tmp:
        save_ply(random_surfels(np.random.default_rng(0), n=N, sh_degree=1), tmp / "ours.ply")
        return (tmp / "ours.ply").read_bytes()


LAYOUTS = ["2dgs", "3dgs", "comgs", "r3dg", "irgs"]


@functools.lru_cache(maxsize=1)
def _valid_files() -> dict[str, bytes]:
    files = {lay: _ply_bytes(_columns(lay)) for lay in LAYOUTS}
    files["3dgs_ascii"] = _ply_bytes(_columns("3dgs"), text=True)
    files["2dgs_big_endian"] = _ply_bytes(_columns("2dgs"), byte_order=">")
    files["ours"] = _ours_bytes()
    return files


def _header_len(data: bytes) -> int:
    i = data.find(b"end_header")
    return i + len("end_header\n") if i >= 0 else len(data)


def _check_load(path) -> None:
    """The contract for one file: finite surfels, or a clear error naming it."""
    try:
        with time_limit(20):
            params = load_ply(path)
    except Exception as e:  # noqa: BLE001 - the contract is checked on any exception
        check_clear_error(e, path)
        return
    assert isinstance(params, SurfelParams) and params.count >= 1
    for k, v in params.to_numpy().items():
        assert np.all(np.isfinite(v)), f"{path}: silent non-finite '{k}' after a successful load"


@pytest.mark.parametrize("name", ["2dgs", "3dgs", "comgs", "r3dg", "irgs", "3dgs_ascii",
                                  "2dgs_big_endian", "ours"])
def test_valid_layouts_load(name, tmp_path):
    path = write(tmp_path / f"{name}.ply", _valid_files()[name])
    p = load_ply(path)
    assert p.count == N
    assert all(np.all(np.isfinite(v)) for v in p.to_numpy().values())


# --------------------------------------------------------------------- byte damage
_NAMES = ["2dgs", "3dgs", "comgs", "r3dg", "irgs", "3dgs_ascii", "2dgs_big_endian", "ours"]


def _byte_damage_test(n_examples):
    @fuzz(n_examples)
    @given(name=st.sampled_from(_NAMES), data=st.data())
    def run(name, data):
        with scratch() as tmp:
            src = _valid_files()[name]
            bad = data.draw(mutated_bytes(src, _header_len(src)))
            _check_load(write(tmp / "damaged.ply", bad))
    return run


def test_byte_damage():
    """Truncation, flipped bytes (anywhere / in the header), random bytes, empty files."""
    _byte_damage_test(500)()


@slow
def test_byte_damage_many():
    _byte_damage_test(1500)()


# --------------------------------------------------------------------- structural damage
@st.composite
def _structural(draw):
    """(bytes, what) of a layout with one structural defect."""
    lay = draw(st.sampled_from(LAYOUTS))
    cols = _columns(lay)
    dtypes = {}
    kind = draw(st.sampled_from(["drop", "dtype", "nonfinite", "count", "keyword", "zero_quat",
                                 "zero_rows", "extra_scale", "rest_gap", "huge_double"]))
    names = list(cols)
    if kind == "drop":
        del cols[draw(st.sampled_from(names))]
    elif kind == "dtype":
        dtypes[draw(st.sampled_from(names))] = draw(st.sampled_from(
            ["u1", "i1", "i2", "u2", "i4", "u4", "f8"]))
    elif kind == "nonfinite":
        p = draw(st.sampled_from(names))
        cols[p] = cols[p].copy()
        cols[p][draw(st.integers(0, N - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    elif kind == "zero_quat":
        for i in range(4):
            cols[f"rot_{i}"] = cols[f"rot_{i}"].copy()
            cols[f"rot_{i}"][0] = 0.0
    elif kind == "zero_rows":
        cols = {k: v[:0] for k, v in cols.items()}
    elif kind == "extra_scale":
        cols["scale_2"], cols["scale_3"] = cols["scale_0"], cols["scale_1"]
    elif kind == "rest_gap":
        cols["f_rest_77"] = cols["x"]
    elif kind == "huge_double":
        p = draw(st.sampled_from(names))
        dtypes[p] = "f8"
        cols[p] = np.full(N, draw(st.sampled_from([1e300, -1e300, 3.5e38])))
    data = _ply_bytes(cols, dtypes, text=draw(st.booleans()))
    if kind == "count":          # header claims another number of vertices
        count = draw(st.sampled_from([0, 1, N + 1, 2 ** 31 - 1, 2 ** 32, 10 ** 12, 10 ** 30,
                                      -1]))
        data = re.sub(rb"element vertex \d+", b"element vertex %d" % count, data, count=1)
    elif kind == "keyword":      # a misspelt or unknown header keyword / property type
        old, new = draw(st.sampled_from([(b"property float", b"property flaot"),
                                         (b"element vertex", b"element vertx"),
                                         (b"format ", b"fromat "),
                                         (b"end_header", b"end_headr"),
                                         (b"property float x", b"property list uchar float x")]))
        data = data.replace(old, new, 1)
    return data, kind


def _structural_test(n_examples):
    @fuzz(n_examples)
    @given(case=_structural())
    def run(case):
        data, _ = case
        with scratch() as tmp:
            _check_load(write(tmp / "structural.ply", data))
    return run


def test_structural_damage():
    """Dropped properties, other dtypes, NaN/Inf cells, header counts from 0 to 10^30,
    misspelt keywords, zero quaternions, zero rows, extra scales, gaps in f_rest."""
    _structural_test(500)()


@slow
def test_structural_damage_many():
    _structural_test(1500)()


@pytest.mark.parametrize("count", [2 ** 32, 10 ** 12])
def test_huge_vertex_count_is_refused_quickly(count, tmp_path):
    """A header claiming ~10^12 vertices on a tiny file: a clear error, no huge allocation."""
    data = re.sub(rb"element vertex \d+", b"element vertex %d" % count,
                  _ply_bytes(_columns("3dgs")), count=1)
    path = write(tmp_path / "huge.ply", data)
    with time_limit(20), pytest.raises(SurfelFileError) as ei:
        load_ply(path)
    check_clear_error(ei.value, path)


def test_nan_property_names_file_and_property(tmp_path):
    cols = _columns("comgs")
    cols["roughness"] = cols["roughness"].copy()
    cols["roughness"][2] = np.nan
    path = write(tmp_path / "nan.ply", _ply_bytes(cols))
    with pytest.raises(SurfelFileError, match="roughness") as ei:
        load_ply(path)
    check_clear_error(ei.value, path)


@pytest.mark.parametrize("what", ["missing", "folder"])
def test_missing_or_folder(what, tmp_path):
    path = tmp_path / "nope.ply"
    if what == "folder":
        path.mkdir()
    with pytest.raises((FileNotFoundError, IsADirectoryError, SurfelFileError)) as ei:
        load_ply(path)
    check_clear_error(ei.value, path)


def test_surfels_plugin_names_the_corrupt_file(tmp_path):
    """The ``surfels`` shape (XML / load_dict) passes the parser's message through."""
    import mitsuba as mi
    from conftest import error_chain_text
    path = write(tmp_path / "cut.ply", _ply_bytes(_columns("2dgs"))[:-7])
    with pytest.raises(Exception) as ei:
        mi.load_dict({"type": "scene", "s": {"type": "surfels", "filename": str(path)}})
    text = error_chain_text(ei.value)
    assert str(path) in text and "truncated" in text


# --------------------------------------------------------------------- .splat
def _splat_bytes(n=N, seed=0) -> bytes:
    rng = np.random.default_rng(seed)
    a = np.zeros(n, dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4),
                           ("rot", "u1", 4)])
    a["pos"] = rng.normal(size=(n, 3))
    a["scale"] = rng.uniform(0.01, 0.1, (n, 3))
    a["rgba"] = rng.integers(0, 256, (n, 4))
    q = rng.normal(size=(n, 4))
    a["rot"] = np.clip(q / np.linalg.norm(q, axis=1, keepdims=True) * 128 + 128, 0, 255)
    return a.tobytes()


def _splat_test(n_examples):
    @fuzz(n_examples)
    @given(data=st.data())
    def run(data):
        with scratch() as tmp:
            path = write(tmp / "d.splat", data.draw(mutated_bytes(_splat_bytes())))
            try:
                with time_limit(20):
                    params = load_splat(path)
            except Exception as e:  # noqa: BLE001
                check_clear_error(e, path)
                return
            assert all(np.all(np.isfinite(v)) for v in params.to_numpy().values())
    return run


def test_splat_damage():
    _splat_test(300)()


@slow
def test_splat_damage_many():
    _splat_test(1500)()


@pytest.mark.parametrize("field,value", [("pos", np.nan), ("scale", np.inf), ("scale", 0.0),
                                         ("scale", -1.0)])
def test_splat_bad_values(field, value, tmp_path):
    a = np.frombuffer(_splat_bytes(), dtype=[("pos", "<f4", 3), ("scale", "<f4", 3),
                                             ("rgba", "u1", 4), ("rot", "u1", 4)]).copy()
    a[field][1, 0] = value
    path = write(tmp_path / "bad.splat", a.tobytes())
    with pytest.raises(SurfelFileError) as ei:
        load_splat(path)
    check_clear_error(ei.value, path)


def test_splat_zero_quaternion(tmp_path):
    a = np.frombuffer(_splat_bytes(), dtype=[("pos", "<f4", 3), ("scale", "<f4", 3),
                                             ("rgba", "u1", 4), ("rot", "u1", 4)]).copy()
    a["rot"][0] = 128                           # (128 - 128) / 128 = 0 in every component
    path = write(tmp_path / "q.splat", a.tobytes())
    with pytest.raises(SurfelFileError, match="quaternion") as ei:
        load_splat(path)
    check_clear_error(ei.value, path)


def test_splat_missing(tmp_path):
    with pytest.raises(FileNotFoundError) as ei:
        load_splat(tmp_path / "nope.splat")
    check_clear_error(ei.value, tmp_path / "nope.splat")


# --------------------------------------------------------------------- writing
def _params(**override):
    from conftest import random_surfels
    d = random_surfels(np.random.default_rng(1), n=N).to_numpy()
    d.update(override)
    return SurfelParams.from_numpy(**d)


@pytest.mark.parametrize("field", ["means", "log_scales", "opacity_logit", "sh", "albedo"])
def test_save_refuses_nan_and_writes_nothing(field, tmp_path):
    d = _params().to_numpy()
    d[field] = d[field].copy()
    d[field].reshape(N, -1)[3, 0] = np.nan
    target = tmp_path / "out.ply"
    with pytest.raises(ValueError, match=field):
        save_ply(SurfelParams.from_numpy(**d), target)
    assert list(tmp_path.iterdir()) == []


def test_save_interrupted_leaves_no_partial_file(tmp_path, monkeypatch):
    """A write that dies half way (disk full) leaves neither a partial target nor litter,
    and an existing file at the target is kept intact."""
    target = tmp_path / "out.ply"
    save_ply(_params(), target)
    before = target.read_bytes()

    def dying_write(self, stream):
        f = open(stream, "wb") if isinstance(stream, (str, bytes)) or hasattr(stream, "__fspath__") \
            else stream
        f.write(b"ply\nformat binary_little_endian 1.0\n")
        f.flush()
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(plyfile.PlyData, "write", dying_write)
    with pytest.raises(OSError):
        save_ply(_params(), target)
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.ply"]
    target.unlink()
    with pytest.raises(OSError):
        save_ply(_params(), target)
    assert list(tmp_path.iterdir()) == []


def test_save_into_missing_folder_is_clear(tmp_path):
    target = tmp_path / "no" / "such" / "dir" / "out.ply"
    with pytest.raises(FileNotFoundError) as ei:
        save_ply(_params(), target)
    assert "no/such/dir" in str(ei.value) or str(target.parent) in str(ei.value)
