"""``comgs reconstruct PHOTOS``: a folder of photos (or a video) is run through ``comgs sfm``
first, into RUN/sfm or --sfm-out, reused when complete; the errors a user meets exit 2."""
import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from comgs_dr import cli
from comgs_dr.cli.sfm import sfm_if_photos
from comgs_dr.stages import sfm as S
from test_sfm import _cameras, _render, _texture

pytest.importorskip("pycolmap")

N_VIEWS = 12


@pytest.fixture(scope="module")
def photos_dir(tmp_path_factory):
    """12 rendered photos of three textured planes (tests/test_sfm.py's capture), nothing
    else: no poses, no masks."""
    root = tmp_path_factory.mktemp("capture") / "photos"
    root.mkdir()
    textures = [_texture(s) for s in (1, 2, 3)]
    for i, (eye, rot) in enumerate(_cameras(N_VIEWS)):
        Image.fromarray(_render(eye, rot, textures)).save(root / f"IMG_{i:04d}.jpg", quality=95)
    return root


def _args(**kw):
    """The namespace ``comgs reconstruct`` parses, SfM flags only."""
    p = cli.build_parser()
    ns = p.parse_args(["reconstruct", "DATA", "--out", "RUN", "--threads", "2", "--max-size", "0"])
    for k, v in kw.items():
        setattr(ns, k, v)
    return ns


@pytest.fixture(scope="module")
def first_run(photos_dir, tmp_path_factory):
    run = tmp_path_factory.mktemp("run")
    data_dir, report = sfm_if_photos(photos_dir, run, _args(), progress=False)
    return run, data_dir, report


def test_photos_run_sfm_into_run_sfm(first_run):
    run, data_dir, report = first_run
    assert data_dir == run / "sfm" and not report["reused"]
    assert report["registered"] == report["given"] == N_VIEWS
    assert (run / "sfm" / "sparse" / "0" / "cameras.bin").is_file()
    assert json.loads((run / "sfm" / "sfm.json").read_text())["source_fingerprint"]


def test_a_complete_output_is_reused_and_a_changed_one_is_not(first_run, photos_dir, capsys):
    run, _, _ = first_run
    data_dir, report = sfm_if_photos(photos_dir, run, _args(threads=1), progress=False)
    assert report["reused"] and data_dir == run / "sfm"          # threads: same result
    assert "reused the earlier structure from motion" in capsys.readouterr().out
    cfg = S.SfmConfig(threads=2, max_size=0)
    assert S.reusable_output(photos_dir, run / "sfm", cfg)[0] is not None
    r, why = S.reusable_output(photos_dir, run / "sfm", S.SfmConfig(max_size=0, max_features=128))
    assert r is None and "max_features 4096 -> 128" in why
    assert S.reusable_output(photos_dir, run / "nothing", cfg)[1].startswith("no sfm.json")
    # a photo changed (its size or time): the photos differ
    p = photos_dir / "IMG_0000.jpg"
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10 ** 9))
    try:
        r, why = S.reusable_output(photos_dir, run / "sfm", cfg)
        assert r is None and "differ" in why
    finally:
        os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_a_checkpoint_on_other_cameras_is_not_resumed(first_run, photos_dir, tmp_path):
    """RUN holds a step-1 checkpoint and the SfM would be redone (other settings): its new
    cameras would not fit the checkpoint, so exit 2 before any work."""
    run, _, _ = first_run
    out = tmp_path / "run"
    out.mkdir()
    (out / "checkpoint.npz").write_bytes(b"x")
    with pytest.raises(ValueError, match="would be made anew.*max_features 4096 -> 128"):
        sfm_if_photos(photos_dir, out, _args(sfm_out=str(run / "sfm"), sfm_max_features=128),
                      progress=False)
    data_dir, report = sfm_if_photos(photos_dir, out, _args(sfm_out=str(run / "sfm")),
                                     progress=False)                 # the same: resumed
    assert report["reused"]


def test_a_dataset_is_used_as_it_is(first_run, capsys):
    run, _, _ = first_run
    data_dir, report = sfm_if_photos(run / "sfm", run / "x", _args(sfm_out="S"), progress=False)
    assert data_dir == run / "sfm" and report is None and not (run / "x").exists()
    assert "SfM flags (sfm_out, max_size, threads) are not used" in capsys.readouterr().err


def test_reconstruct_trains_on_the_photos(first_run, photos_dir, capsys):
    """The command end to end on the photos, the SfM reused from the fixture's RUN/sfm
    (--sfm-out): scene preset, run.json names the SfM output, the sparse points are the
    init."""
    run, _, _ = first_run
    out = run.parent / "train"
    rc = cli.main(["reconstruct", str(photos_dir), "--out", str(out), "--sfm-out",
                   str(run / "sfm"), "--threads", "2", "--max-size", "0", "--iterations", "2",
                   "--eval-every", "1000", "--eval-views", "1", "--resolution-scale", "4",
                   "--quiet"])
    o = capsys.readouterr().out
    assert rc == 0, o
    assert "reused the earlier structure from motion" in o and "scene preset" in o
    info = json.loads((out / "run.json").read_text())
    assert info["preset"] == "scene" and Path(info["data"]) == (run / "sfm").resolve()
    assert (out / "point_cloud.ply").is_file()


@pytest.mark.parametrize("setup, message", [
    (lambda d: d / "missing", "no such file or folder"),
    (lambda d: (d / "notes.txt").write_text("x") and d / "notes.txt", "not a dataset folder"),
    (lambda d: (d / "e").mkdir() or d / "e", "nor does it hold photos"),
    (lambda d: _two_photos(d), "at least 3"),
])
def test_bad_input_exits_2_naming_it(tmp_path, capsys, setup, message):
    src = setup(tmp_path)
    assert cli.main(["reconstruct", str(src), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and str(src) in err, err
    assert not (tmp_path / "run" / "run.json").exists()


def test_bad_sfm_flag_exits_2_before_any_work(tmp_path, capsys, photos_dir):
    out = tmp_path / "run"
    assert cli.main(["reconstruct", str(photos_dir), "--out", str(out), "--max-size", "10"]) == 2
    assert "max_size must be 0 or >= 64" in capsys.readouterr().err and not out.exists()


def _two_photos(d: Path) -> Path:
    src = d / "two"
    src.mkdir()
    for i in range(2):
        Image.fromarray(np.full((64, 64, 3), 100 + i, np.uint8)).save(src / f"{i}.jpg")
    return src


def test_a_video_is_a_capture(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    video = tmp_path / "clip.mp4"
    w = imageio_ffmpeg.write_frames(str(video), (64, 64), fps=4, macro_block_size=16)
    w.send(None)
    for i in range(4):
        w.send(np.full((64, 64, 3), 60 * i, np.uint8).tobytes())
    w.close()
    assert S.is_unposed_capture(video)
    assert S.source_fingerprint(video) == S.source_fingerprint(video)


@pytest.mark.slow
def test_reconstruct_a_video_end_to_end(photos_dir, tmp_path, capsys):
    """The capture as a 4-fps video: frames sampled, SfM into RUN/sfm, step 1 trained (the
    photo path above is the fast test of the same code; ~25 s on 2 cores)."""
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    video = tmp_path / "clip.mp4"
    w = imageio_ffmpeg.write_frames(str(video), (320, 240), fps=4, quality=9,
                                    macro_block_size=16)
    w.send(None)
    for f in sorted(photos_dir.glob("*.jpg")):
        w.send(np.ascontiguousarray(np.asarray(Image.open(f).convert("RGB"))).tobytes())
    w.close()
    out = tmp_path / "run"
    rc = cli.main(["reconstruct", str(video), "--out", str(out), "--fps", "4", "--blur-group",
                   "1", "--blur-min-ratio", "0", "--threads", "2", "--iterations", "2",
                   "--eval-every", "1000", "--eval-views", "1", "-r", "4", "--quiet"])
    o = capsys.readouterr().out
    assert rc == 0 and "is a video: ran structure from motion" in o, o
    r = json.loads((out / "sfm" / "sfm.json").read_text())
    assert r["kind"] == "video" and r["registered"] >= N_VIEWS - 1
    assert Path(json.loads((out / "run.json").read_text())["data"]) == (out / "sfm").resolve()
