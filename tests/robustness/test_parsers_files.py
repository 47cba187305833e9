"""Placement files, environment maps, run folders, composition folders, probe files and
checkpoints on random and corrupted input.

Contract: the reader returns finite values, or raises a clear error (ValueError /
FileNotFoundError) whose message names the file; no hang; no process crash.
"""
import io
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from robust_util import (
    check_clear_error,
    corrupted_json_bytes,
    fuzz,
    mutated_bytes,
    nerf_folder,
    scratch,
    slow,
    time_limit,
    write,
)


def _contract(fn, path, check_ok=None):
    """Call ``fn(path)``: a clear error naming ``path``, or a result passed to ``check_ok``."""
    try:
        with time_limit(30):
            out = fn(path)
    except Exception as e:  # noqa: BLE001 - the contract is checked on any exception
        check_clear_error(e, path)
        return None
    if check_ok is not None:
        check_ok(out)
    return out


# --------------------------------------------------------------------- placement
PLACEMENTS = {
    "matrix": {"chair": {"transform": [0.5, 0, 0, 1, 0, 0.5, 0, 2, 0, 0, 0.5, 0, 0, 0, 0, 1]}},
    "euler": {"chair": {"location": [1, 2, 0], "rotation": [0, 0, 90], "scale": 0.5},
              "lamp": {"location": [0, 0, 1], "scale": [2, 2, 2]}},
}


def _check_placements(out):
    assert isinstance(out, dict) and out
    for sim in out.values():
        assert np.all(np.isfinite(sim.matrix)) and sim.scale > 0


def _placement_test(n):
    from comgs_dr.core.similarity import read_placements

    @fuzz(n)
    @given(kind=st.sampled_from(sorted(PLACEMENTS)), data=st.data())
    def run(kind, data):
        with scratch() as tmp:
            path = write(tmp / "transform.json", data.draw(corrupted_json_bytes(PLACEMENTS[kind])))
            _contract(read_placements, path, _check_placements)
    return run


def test_placement_damage():
    """transform.json: dropped keys, wrong types (dicts, strings, nested lists), NaN/Inf,
    integers beyond float range, extra keys, empty lists, byte damage, non-UTF-8."""
    _placement_test(400)()


@slow
def test_placement_damage_many():
    _placement_test(3000)()


@pytest.mark.parametrize("entry", [
    {"transform": {"a": 1}}, {"transform": [[1, 0], [0, 1, 0]]}, {"transform": [10 ** 400] * 16},
    {"location": {"x": 1}}, {"location": [1, 2, 10 ** 400]}, {"scale": "big"}, {"scale": 0},
    {"scale": [1, 2]}, {"rotation": [None, 0, 0]}, {"transform": [float("nan")] * 16},
])
def test_placement_bad_entries(entry, tmp_path):
    from comgs_dr.core.similarity import read_placements
    path = tmp_path / "transform.json"
    path.write_text(json.dumps({"chair": entry}))
    with pytest.raises(ValueError) as ei:
        read_placements(path)
    check_clear_error(ei.value, path)
    assert "chair" in str(ei.value)


# --------------------------------------------------------------------- environment maps
def _env_bytes(ext: str) -> bytes:
    import mitsuba as mi

    from comgs_dr.lighting import envmap as em
    img = np.random.default_rng(0).uniform(0, 5, (8, 16, 3)).astype(np.float32)
    with scratch() as tmp:
        if ext == "exr":
            em.write_exr(tmp / "m.exr", img, "equirect")
        else:
            mi.Bitmap(img).write(str(tmp / "m.hdr"))
        return (tmp / f"m.{ext}").read_bytes()


def _check_env(out):
    arr, layout = out
    assert layout in ("equirect", "octahedral")
    assert arr.ndim == 3 and arr.shape[2] == 3
    assert np.all(np.isfinite(arr)) and arr.min() >= 0, "silent NaN/Inf/negative radiance"


def _exr_test(n):
    from comgs_dr.lighting.envmap import read_envmap_file
    good = _env_bytes("exr")

    @fuzz(n)
    @given(data=st.data())
    def run(data):
        with scratch() as tmp:
            path = write(tmp / "env.exr", data.draw(mutated_bytes(good, 400)))
            _contract(read_envmap_file, path, _check_env)
    return run


def test_envmap_exr_damage():
    """EXR maps: truncation, flipped header/pixel bytes, random bytes, empty files."""
    _exr_test(200)()


@slow
def test_envmap_exr_damage_many():
    _exr_test(1500)()


@st.composite
def _hdr_damage(draw, good):
    """Radiance .hdr damage: truncation, random bytes, header text edits, flipped bytes in
    the header or inside the RLE scanlines (these crashed Mitsuba's reader: see
    test_envmap_hdr_damaged_scanline_marker_is_an_error)."""
    kind = draw(st.sampled_from(["truncate", "random", "empty", "header", "bytes", "marker"]))
    if kind == "bytes":
        return draw(mutated_bytes(good, 60))
    if kind == "marker":            # a scanline's RLE marker 02 02 hi lo damaged
        marks = [i for i in range(len(good)) if good[i:i + 2] == b"\x02\x02"]
        raw = bytearray(good)
        raw[draw(st.sampled_from(marks)) + draw(st.integers(0, 3))] = draw(st.integers(0, 255))
        return bytes(raw)
    if kind == "truncate":
        return good[: draw(st.integers(0, len(good) - 1))]
    if kind == "random":
        return draw(st.binary(min_size=1, max_size=200))
    if kind == "empty":
        return b""
    old, new = draw(st.sampled_from([(b"-Y 8", b"-Y 0"), (b"-Y 8", b"-Y 99999999"),
                                     (b"+X 16", b"+X -3"), (b"32-bit_rle_rgbe", b"32-bit_rle_xyze"),
                                     (b"#?", b"#!"), (b"-Y 8 +X 16", b"+X 16 -Y 8"),
                                     (b"-Y 8", b"-Y 4")]))
    return good.replace(old, new, 1)


def _hdr_test(n):
    from comgs_dr.lighting.envmap import read_envmap_file
    good = _env_bytes("hdr")

    @fuzz(n)
    @given(raw=_hdr_damage(good))
    def run(raw):
        with scratch() as tmp:
            path = write(tmp / "env.hdr", raw)
            _contract(read_envmap_file, path, _check_env)
    return run


def test_envmap_hdr_damage():
    _hdr_test(100)()


@slow
def test_envmap_hdr_damage_many():
    _hdr_test(600)()


@pytest.mark.parametrize("scanline", [1, 7])
def test_envmap_hdr_damaged_scanline_marker_is_an_error(scanline, tmp_path):
    """Runs in a child process: the failure mode is a crash of the whole interpreter."""
    raw = bytearray(_env_bytes("hdr"))
    marks = [i for i in range(len(raw)) if raw[i:i + 4] == b"\x02\x02\x00\x10"]   # 16 px wide
    assert len(marks) == 8
    raw[marks[scanline] + 1] = 0xB8
    path = write(tmp_path / "env.hdr", bytes(raw))
    code = textwrap.dedent(f"""
        import comgs_dr
        comgs_dr.set_variant("llvm_ad_rgb")
        from comgs_dr.lighting.envmap import read_envmap_file
        try:
            read_envmap_file({str(path)!r})
        except ValueError as e:
            assert {str(path)!r} in str(e), e
            print("CLEAR ERROR")
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "CLEAR ERROR" in r.stdout, (r.returncode, r.stderr[-300:])


@pytest.mark.parametrize("reader,content", [
    (r, c) for r in ("read_envmap_file", "load_envmap")
    for c in ("missing", "folder", "empty", "text", "nan")] + [("read_envmap_file", "square")])
def test_envmap_bad_files(reader, content, tmp_path):
    """Missing, a folder, empty, text, a NaN texel, a square map without layout metadata."""
    import mitsuba as mi

    from comgs_dr.lighting import envmap as em
    path = tmp_path / "env.exr"
    if content == "folder":
        path.mkdir()
    elif content == "empty":
        path.write_bytes(b"")
    elif content == "text":
        path.write_text("not an image")
    elif content in ("nan", "square"):
        img = np.ones((8, 8 if content == "square" else 16, 3), np.float32)
        img[2, 3, 1] = np.nan if content == "nan" else 1.0
        mi.Bitmap(img).write(str(path))
    with pytest.raises((ValueError, FileNotFoundError, IsADirectoryError)) as ei:
        getattr(em, reader)(path)
    check_clear_error(ei.value, path)


# --------------------------------------------------------------------- run folders
RUN_INFO = {"data": "/nonexistent/data", "preset": "object", "resolution_scale": 1,
            "white_background": False}


def _run_info_test(n):
    from comgs_dr.train.run import RUN_FILE, load_run_dataset, read_run_info

    def read_and_load(path):
        info = read_run_info(path.parent)
        try:
            load_run_dataset(path.parent, info)
        except (FileNotFoundError, ValueError) as e:
            if "/nonexistent/data" in str(e) or str(info.get("data")) in str(e):
                return info              # the dataset itself is missing: a clear error
            raise
        return info

    @fuzz(n)
    @given(data=st.data())
    def run(data):
        with scratch() as tmp:
            path = write(tmp / "run" / RUN_FILE, data.draw(corrupted_json_bytes(RUN_INFO)))
            _contract(read_and_load, path)
    return run


def test_run_json_damage():
    """run.json: wrong types, missing keys, extra keys, byte damage, non-UTF-8."""
    _run_info_test(300)()


@slow
def test_run_json_damage_many():
    _run_info_test(2000)()


def test_render_on_corrupt_run_folder(tmp_path, capsys):
    """``comgs render`` on a damaged run.json, a missing one, a truncated point_cloud.ply:
    exit 2 with a message naming the file, no traceback."""
    from conftest import random_surfels

    from comgs_dr import cli
    from comgs_dr.surfels import save_ply
    from comgs_dr.train.run import write_run_info
    data = nerf_folder(tmp_path / "data")
    run = tmp_path / "run"
    write_run_info(run, data, "object", 1, False)
    save_ply(random_surfels(np.random.default_rng(0), n=20), run / "point_cloud.ply")
    assert cli.main(["render", str(run), "--quiet"]) == 0         # the intact folder renders
    capsys.readouterr()
    good_info, good_ply = (run / "run.json").read_bytes(), (run / "point_cloud.ply").read_bytes()
    cases = [("run.json", b"{\"data\": "), ("run.json", b"\xff\xfe{}"), ("run.json", b"[1, 2]"),
             ("run.json", json.dumps({"data": str(data)}).encode()),
             ("point_cloud.ply", good_ply[:-9]), ("point_cloud.ply", b"")]
    for name, raw in cases:
        (run / "run.json").write_bytes(good_info)
        (run / "point_cloud.ply").write_bytes(good_ply)
        (run / name).write_bytes(raw)
        assert cli.main(["render", str(run), "--quiet"]) == 2, (name, raw)
        err = capsys.readouterr().err
        assert str(run / name) in err and "Traceback" not in err, (name, raw, err)


# --------------------------------------------------------------------- composition folders
def _manifest_test(n):
    from comgs_dr.data.comp_folder import MANIFEST, read_manifest
    doc = {"version": 1, "scene": {"run": "/r", "ply": "/r/point_cloud.ply",
                                   "colour_space": "srgb"},
           "world_from_source": np.eye(4).tolist(),
           "objects": {"chair": {"run": "/o", "ply": "/o/p.ply", "placement": np.eye(4).tolist(),
                                 "envmap": "env/chair.exr", "probes": "probes/chair.npz",
                                 "bounds": [[0, 0, 0], [1, 1, 1]]}},
           "shadow_probes": "shadow_probes.npz", "config": {}}

    @fuzz(n)
    @given(data=st.data())
    def run(data):
        with scratch() as tmp:
            path = write(tmp / MANIFEST, data.draw(corrupted_json_bytes(doc)))
            _contract(lambda p: read_manifest(p.parent), path)
    return run


def test_composition_manifest_damage():
    _manifest_test(300)()


@slow
def test_composition_manifest_damage_many():
    _manifest_test(2000)()


def _check_cameras(out):
    assert out
    for c in out:
        assert np.all(np.isfinite(c["to_world"])) and 0 < c["fov_x_deg"] < 180
        assert c["width"] is None or c["width"] >= 1


def _cameras_test(n):
    from comgs_dr.data.comp_folder import read_cameras
    doc = {"camera_angle_x": 0.7, "w": 16, "h": 12,
           "frames": [{"file_path": "./test/r_0", "transform_matrix": np.eye(4).tolist()},
                      {"file_path": "./test/r_1", "transform_matrix": np.eye(4).tolist()}]}

    @fuzz(n)
    @given(data=st.data())
    def run(data):
        with scratch() as tmp:
            path = write(tmp / "transforms_test.json", data.draw(corrupted_json_bytes(doc)))
            _contract(read_cameras, path, _check_cameras)
    return run


def test_render_comp_cameras_damage():
    """The camera file of ``comgs render-comp`` (NeRF-synthetic transforms json)."""
    _cameras_test(300)()


@slow
def test_render_comp_cameras_damage_many():
    _cameras_test(2000)()


# --------------------------------------------------------------------- probe files
def _probe_bytes() -> bytes:
    from comgs_dr.sops.probes import ProbeSet
    rng = np.random.default_rng(0)
    ps = ProbeSet(rng.normal(size=(3, 3)), np.tile([0.0, 0.0, 1.0], (3, 1)), 2, 0.5,
                  texture=rng.uniform(0, 1, (3, 2, 2, 4)))
    with scratch() as tmp:
        return ps.save(tmp / "p.npz").read_bytes()


@st.composite
def _probe_damage(draw, good):
    if draw(st.booleans()):
        return draw(mutated_bytes(good, 200))
    with np.load(io.BytesIO(good)) as z:
        arrays = {k: z[k] for k in z.files}
    key = draw(st.sampled_from(sorted(arrays)))
    kind = draw(st.sampled_from(["drop", "nan", "shape", "meta"]))
    if kind == "drop":
        del arrays[key]
    elif kind == "nan" and arrays[key].dtype.kind == "f" and arrays[key].size:
        arrays[key] = arrays[key].copy()
        arrays[key].flat[0] = draw(st.sampled_from([np.nan, np.inf, -1.0, 0.0]))
    elif kind == "shape":
        arrays[key] = np.zeros(draw(st.sampled_from([(), (2,), (0, 3), (3, 5)])),
                               arrays[key].dtype if arrays[key].dtype.kind != "U" else "f4")
    else:
        arrays["meta"] = np.array(draw(st.sampled_from(['[1, 2]', '"x"', '{"version": 99}',
                                                        '{"version": "a"}', 'null', '{'])))
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _probes_test(n):
    from comgs_dr.sops.probes import ProbeSet
    good = _probe_bytes()

    def check(ps):
        assert np.all(np.isfinite(ps.positions)) and np.all(np.isfinite(ps.normals))
        assert ps.texture is None or np.all(np.isfinite(ps.texture))

    @fuzz(n)
    @given(raw=_probe_damage(good))
    def run(raw):
        with scratch() as tmp:
            _contract(ProbeSet.load, write(tmp / "probes.npz", raw), check)
    return run


def test_probe_file_damage():
    _probes_test(300)()


def test_probe_file_of_pickled_objects_is_refused_without_unsafe_advice(tmp_path):
    from comgs_dr.sops.probes import ProbeSet
    np.savez(tmp_path / "p.npz", meta=np.array([{"a": 1}], dtype=object), texture=np.zeros(1))
    with pytest.raises(ValueError, match="pickled Python objects, not a probe file") as ei:
        ProbeSet.load(tmp_path / "p.npz")
    assert "allow_pickle" not in str(ei.value)


@slow
def test_probe_file_damage_many():
    _probes_test(2000)()


# --------------------------------------------------------------------- checkpoints
def _checkpoint_bytes() -> bytes:
    from comgs_dr.train import checkpoint as ck

    class _NoOpt:
        state = {}
    with scratch() as tmp:
        ck.save_checkpoint(tmp / "c.npz", "fmt/1", {"x": np.arange(4.0)}, _NoOpt(), {},
                           {"iteration": 3})
        return (tmp / "c.npz").read_bytes()


def test_checkpoint_byte_damage():
    """``load_checkpoint`` on truncated, flipped, random or empty files."""
    from comgs_dr.train.checkpoint import load_checkpoint
    good = _checkpoint_bytes()

    @fuzz(150)
    @given(raw=mutated_bytes(good, 120))
    def run(raw):
        with scratch() as tmp:
            _contract(lambda p: load_checkpoint(p, "fmt/1"), write(tmp / "checkpoint.npz", raw))
    run()


@pytest.mark.parametrize("state,arrays", [
    (b"", {}), (b"\xff\xfe", {}), (b'{"format": 3}', {}),
    (b"[1, 2]", {}), (b'"fmt/1"', {}), (b'{"format": "fmt/1"}', {"m_x": np.zeros(4)}),
])
def test_checkpoint_bad_state(state, arrays, tmp_path):
    from comgs_dr.train.checkpoint import load_checkpoint
    path = tmp_path / "checkpoint.npz"
    np.savez(path, p_x=np.arange(4.0), state=np.frombuffer(state, np.uint8), **arrays)
    with pytest.raises(ValueError) as ei:
        load_checkpoint(path, "fmt/1")
    check_clear_error(ei.value, path)


def _run_with_checkpoint(tmp_path, folder: str, arrays: dict, state: dict | None):
    """A tiny NeRF dataset, a step-1 run (surfels + run.json) and ``folder/checkpoint.npz``
    holding ``arrays`` and ``state`` (JSON; None: random bytes)."""
    from conftest import random_surfels

    from comgs_dr.surfels import save_ply
    from comgs_dr.train.run import write_run_info
    data = nerf_folder(tmp_path / "data")
    run = tmp_path / "run"
    write_run_info(run, data, "object", 1, False)
    save_ply(random_surfels(np.random.default_rng(0), n=20), run / "point_cloud.ply")
    ck = run / folder / "checkpoint.npz"
    ck.parent.mkdir(parents=True, exist_ok=True)
    if state is None:
        ck.write_bytes(b"PK\x03\x04" + bytes(range(200)))
    else:
        np.savez(ck, **arrays, state=np.frombuffer(json.dumps(state).encode(), np.uint8))
    return data, run, ck


@pytest.mark.parametrize("arrays,state", [
    ({}, None),
    ({}, {"format": "comgs_dr.checkpoint/1"}),
    pytest.param({f"p_{k}": np.zeros((3, 2)) for k in (
        "means", "quats", "log_scales", "opacity_logit", "sh", "albedo", "roughness",
        "metallic")}, {"format": "comgs_dr.checkpoint/1",
                                                  "iteration": 1, "log": [], "elapsed": 0.0,
                                                  "init": "x"}),
], ids=["damaged", "no-arrays", "wrong-shape"])
def test_reconstruct_resume_from_corrupt_checkpoint(arrays, state, tmp_path, capsys):
    """``comgs reconstruct`` resuming from a damaged or inconsistent checkpoint: exit 2
    naming the checkpoint, no traceback."""
    from comgs_dr import cli
    data, run, ck = _run_with_checkpoint(tmp_path, ".", arrays, state)
    code = cli.main(["reconstruct", str(data), "--out", str(run), "--iterations", "2",
                     "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    assert "checkpoint" in err and run.name in err, err


@pytest.mark.parametrize("state", [None, {"format": "comgs_dr.material_checkpoint/2",
                                          "config": {"visibility": "trace"}}],
                         ids=["damaged", "other-visibility"])
def test_decompose_resume_from_corrupt_checkpoint(state, tmp_path, capsys):
    from comgs_dr import cli
    data, run, ck = _run_with_checkpoint(tmp_path, "material", {}, state)
    code = cli.main(["decompose", str(run), "--iterations", "2", "--rays", "2", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    assert str(ck) in err, err
