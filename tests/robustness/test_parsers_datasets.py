"""Dataset folders (NeRF-synthetic JSON, LLFF ``poses_bounds.npy``, COLMAP text and binary
models, ``points3d.ply``, images) on random and corrupted input.

Contract: ``load_dataset`` returns finite cameras and images, or raises a clear error
(DatasetError / FileNotFoundError) whose message names a path inside the folder; no hang
(a corrupted binary COLMAP count used to make COLMAP loop ~2^63 times).
"""
import io
import json
import shutil

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image
from robust_util import (
    H,
    W,
    check_clear_error,
    corrupted_json_bytes,
    fuzz,
    mutated_bytes,
    nerf_doc,
    nerf_folder,
    png_bytes,
    scratch,
    slow,
    time_limit,
    write,
)

from comgs_dr.data.load import load_dataset


def _check(root) -> None:
    """Load ``root``: finite cameras/images, or a clear error naming a path in it."""
    try:
        with time_limit(30):
            data = load_dataset(root)
    except Exception as e:  # noqa: BLE001 - the contract is checked on any exception
        check_clear_error(e, root)
        return
    assert data.train, "a dataset loaded without training views"
    for v in data.train + data.test:
        assert np.all(np.isfinite(v.camera.to_world)) and np.isfinite(v.camera.fov_x_deg)
        assert np.all(np.isfinite(v.image)) and v.image.min() >= 0 and v.image.max() <= 1
    if data.points is not None:
        assert np.all(np.isfinite(data.points))


# --------------------------------------------------------------------- NeRF-synthetic
def test_valid_nerf_loads(tmp_path):
    data = load_dataset(nerf_folder(tmp_path))
    assert len(data.train) == 2 and len(data.test) == 1


def _nerf_json_test(n):
    @fuzz(n)
    @given(split=st.sampled_from(["train", "test"]), data=st.data())
    def run(split, data):
        raw = data.draw(corrupted_json_bytes(nerf_doc(split, 2 if split == "train" else 1)))
        with scratch() as tmp:
            _check(nerf_folder(tmp, {split: raw}))
    return run


def test_nerf_json_damage():
    """transforms_*.json: dropped keys, wrong types, NaN/Inf/huge values, extra keys,
    empty lists, other documents, byte damage, non-UTF-8 text."""
    _nerf_json_test(300)()


@slow
def test_nerf_json_damage_many():
    _nerf_json_test(2000)()


@pytest.mark.parametrize("entry", [
    {"camera_angle_x": 0.8, "w": 0, "h": 6},
    {"fl_x": 7.0, "w": 8, "h": 0},
    {"fl_x": 0.0},
    {"fl_x": -7.0},
    {"fl_x": 1e309},
    {"camera_angle_x": 0.8, "w": "8", "h": None},
    {"camera_angle_x": 0.8, "k1": "x"},
    {"camera_angle_x": [0.8]},
])
def test_nerf_bad_intrinsics(entry, tmp_path):
    """Zero/negative/huge/mistyped intrinsics: a clear error, not ZeroDivisionError."""
    doc = nerf_doc("train")
    doc.pop("camera_angle_x")
    doc.update(entry)
    raw = json.dumps(doc).encode().replace(b"Infinity", b"1e309")
    root = nerf_folder(tmp_path, {"train": raw})
    with pytest.raises(Exception) as ei:
        load_dataset(root)
    check_clear_error(ei.value, root)


def _nerf_image_test(n):
    @fuzz(n)
    @given(data=st.data())
    def run(data):
        bad = data.draw(mutated_bytes(png_bytes(0, alpha=True), 33))
        with scratch() as tmp:
            _check(nerf_folder(tmp, images={"train/r_0.png": bad}))
    return run


def test_nerf_image_damage():
    """A damaged PNG (truncated, flipped header bytes, random bytes, empty)."""
    _nerf_image_test(120)()


@slow
def test_nerf_image_damage_many():
    _nerf_image_test(1000)()


@pytest.mark.parametrize("size", [(0, 0), (100000, 100000), (2 ** 31 - 1, 1)])
def test_nerf_image_claiming_a_huge_size(size, tmp_path):
    """A PNG header claiming no pixels or ~10^10 (a decompression bomb)."""
    buf = io.BytesIO()
    Image.new("RGB", (1, 1)).save(buf, format="PNG")
    raw = bytearray(buf.getvalue())
    raw[16:24] = size[0].to_bytes(4, "big") + size[1].to_bytes(4, "big")   # IHDR width/height
    root = nerf_folder(tmp_path, images={"train/r_0.png": bytes(raw)})
    with time_limit(30), pytest.raises(Exception) as ei:
        load_dataset(root)
    check_clear_error(ei.value, root)


def _points_test(n):
    from comgs_dr.data.sfm_points import write_points_ply
    with scratch() as tmp:
        write_points_ply(tmp / "p.ply", np.random.default_rng(0).normal(size=(6, 3)))
        good = (tmp / "p.ply").read_bytes()

    @fuzz(n)
    @given(data=st.data())
    def run(data):
        with scratch() as tmp:
            root = nerf_folder(tmp)
            write(root / "points3d.ply", data.draw(mutated_bytes(good, good.find(b"end_header"))))
            _check(root)
    return run


def test_points_ply_damage():
    _points_test(150)()


@slow
def test_points_ply_damage_many():
    _points_test(1000)()


# --------------------------------------------------------------------- LLFF
def _poses(n=2) -> np.ndarray:
    rows = []
    for i in range(n):
        r = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # [down, right, back]
        m = np.concatenate([r, [[0.3 * i], [0.0], [4.0]], [[H], [W], [7.0]]], 1)   # [3, 5]
        rows.append(np.concatenate([m.ravel(), [0.5, 9.0]]))
    return np.array(rows)


def _llff(root, pb_bytes: bytes | None = None, n_images: int = 2):
    if pb_bytes is None:
        buf = io.BytesIO()
        np.save(buf, _poses())
        pb_bytes = buf.getvalue()
    write(root / "poses_bounds.npy", pb_bytes)
    for i in range(n_images):
        write(root / "images" / f"IMG_{i}.png", png_bytes(i))
    return root


def test_valid_llff_loads(tmp_path):
    data = load_dataset(_llff(tmp_path))
    assert len(data.train) + len(data.test) == 2


@st.composite
def _poses_array(draw):
    """poses_bounds arrays with one defect: shape, dtype, values."""
    a = _poses()
    kind = draw(st.sampled_from(["shape", "value", "dtype", "rows"]))
    if kind == "shape":
        shape = draw(st.sampled_from([(2, 16), (2, 18), (34,), (2, 17, 1), (0, 17), ()]))
        return np.resize(a, shape)
    if kind == "rows":
        return np.concatenate([a, a[:1]]) if draw(st.booleans()) else a[:1]
    if kind == "value":
        a = a.copy()
        a.flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from(
            [np.nan, np.inf, -np.inf, 0.0, -1.0, 1e300, -1e300, 1e-300]))
        return a
    dt = draw(st.sampled_from(["f4", "f2", "i8", "u1", "c16", "U8", "bool", "object"]))
    return a.astype(dt)


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=True)
    return buf.getvalue()


def _llff_test(n):
    @fuzz(n)
    @given(case=st.one_of(_poses_array().map(_npy),
                          mutated_bytes(_npy(_poses()), 128)))
    def run(case):
        with scratch() as tmp:
            _check(_llff(tmp, case))
    return run


def test_llff_poses_damage():
    """poses_bounds.npy: wrong shapes/row counts, NaN/Inf/zero/huge cells (hwf, poses,
    bounds), other dtypes (ints, complex, strings, pickled objects), byte damage."""
    _llff_test(300)()


@slow
def test_llff_poses_damage_many():
    _llff_test(2000)()


# --------------------------------------------------------------------- COLMAP
_CAMERAS = "# cameras\n1 PINHOLE 8 6 7.0 7.0 4.0 3.0\n"
_IMAGES = ("# images\n1 1 0 0 0 0 0 4 1 a.png\n\n2 1 0 0 0 0.3 0 4 1 b.png\n"
           "1.0 2.0 1 3.0 1.0 -1\n")
_POINTS = "# points\n1 0.1 0.2 0.3 255 0 0 0.5 2 0\n2 0 0 0 1 2 3 0.1\n"
_TEXT = {"cameras.txt": _CAMERAS, "images.txt": _IMAGES, "points3D.txt": _POINTS}


def _colmap(root, files: dict | None = None):
    model = root / "sparse" / "0"
    for name, text in {**_TEXT, **(files or {})}.items():
        write(model / name, text if isinstance(text, bytes) else text.encode())
    write(root / "images" / "a.png", png_bytes(0))
    write(root / "images" / "b.png", png_bytes(1))
    return root


def _binary_model() -> dict[str, bytes]:
    import pycolmap
    with scratch() as tmp:
        _colmap(tmp)
        rec = pycolmap.Reconstruction(str(tmp / "sparse" / "0"))
        out = tmp / "bin"
        out.mkdir()
        rec.write_binary(str(out))
        return {f.name: f.read_bytes() for f in out.iterdir()}


def _colmap_binary(root, files: dict):
    _colmap(root)
    model = root / "sparse" / "0"
    shutil.rmtree(model)
    for name, raw in files.items():
        write(model / name, raw)
    return root


def test_valid_colmap_loads(tmp_path):
    assert len(load_dataset(_colmap(tmp_path / "t")).train) == 1
    data = load_dataset(_colmap_binary(tmp_path / "b", _binary_model()))
    assert len(data.train) == 1 and len(data.test) == 1 and len(data.points) == 2


_TOKENS = ["nan", "inf", "-1", "0", "1e309", "99999999999999999999", "x", "",
           "SIMPLE_RADIAL", "FISHEYE", "\xff"]


@st.composite
def _text_model(draw):
    name = draw(st.sampled_from(sorted(_TEXT)))
    text = _TEXT[name]
    if draw(st.booleans()):             # replace one token
        parts = text.split(" ")
        i = draw(st.integers(0, len(parts) - 1))
        end = "\n" if parts[i].endswith("\n") else ""
        parts[i] = draw(st.sampled_from(_TOKENS)) + end
        return {name: " ".join(parts).encode("utf-8", "surrogateescape")}
    return {name: draw(mutated_bytes(text.encode()))}


def _colmap_text_test(n):
    @fuzz(n)
    @given(files=_text_model())
    def run(files):
        with scratch() as tmp:
            _check(_colmap(tmp, files))
    return run


def test_colmap_text_damage():
    _colmap_text_test(200)()


@slow
def test_colmap_text_damage_many():
    _colmap_text_test(1500)()


@st.composite
def _binary_damage(draw, model):
    files = dict(model)
    name = draw(st.sampled_from(sorted(files)))
    raw = bytearray(files[name])
    kind = draw(st.sampled_from(["bytes", "count64", "count32", "drop"]))
    if kind == "drop":
        del files[name]
        return files
    if kind == "bytes":
        files[name] = draw(mutated_bytes(bytes(raw)))
        return files
    width = 8 if kind == "count64" else 4
    pos = draw(st.integers(0, max(len(raw) - width, 0)))
    value = draw(st.sampled_from([2 ** (8 * width - 1) - 1, 2 ** (8 * width) - 1, 70000]))
    raw[pos:pos + width] = value.to_bytes(width, "little")
    files[name] = bytes(raw)
    return files


def _colmap_binary_test(n):
    model = _binary_model()

    @fuzz(n)
    @given(files=_binary_damage(model))
    def run(files):
        with scratch() as tmp:
            _check(_colmap_binary(tmp, files))
    return run


def test_colmap_binary_damage():
    """cameras/images/points3D/rigs/frames.bin: byte damage and huge 32/64-bit counts at
    every offset (COLMAP itself loops ~2^63 times on a huge frame count)."""
    _colmap_binary_test(300)()


@slow
def test_colmap_binary_damage_many():
    _colmap_binary_test(3000)()


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin", "frames.bin",
                                  "rigs.bin"])
def test_colmap_huge_leading_count_is_refused(name, tmp_path):
    files = _binary_model()
    files[name] = (2 ** 63 - 1).to_bytes(8, "little") + files[name][8:]
    root = _colmap_binary(tmp_path, files)
    with time_limit(30), pytest.raises(Exception) as ei:
        load_dataset(root)
    check_clear_error(ei.value, root)
    assert name in str(ei.value)
