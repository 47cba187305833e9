"""Camera paths of ``comgs render-comp --path`` (issue 49 item 3): orbit, spiral, a
transforms.json; path frames end to end (PNGs, mp4, summary, per-frame intrinsics) and the
clear errors of the command line."""
import json

import numpy as np
import pytest

from comgs_dr.data import camera_path as cp
from comgs_dr.data import comp_folder
from comgs_dr.data.types import MITSUBA_FROM_OPENGL
from comgs_dr.stages.render_comp import RenderCompConfig

CENTRE = np.array([0.3, -0.2, 0.5])


def _capture(n=8, dist=4.0, elev_deg=30.0, w=40, h=30):
    """Cameras on a ring around CENTRE looking at it, intrinsics off the centre."""
    out = []
    for i in range(n):
        az = 0.4 + 2 * np.pi * i / n
        e = np.radians(elev_deg + (5.0 if i % 2 else -5.0))
        eye = CENTRE + dist * np.array([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az),
                                        np.sin(e)])
        out.append(comp_folder.camera(f"c{i}", cp.look_at(eye, CENTRE), w, h, 36.0, 36.0,
                                      18.5, 16.0))
    return out


def _looks_at(m, c):
    f = c - m[:3, 3]
    return np.allclose(m[:3, 2], f / np.linalg.norm(f), atol=1e-9)


def test_orbit_circles_the_centre_at_the_capture_distance_and_elevation():
    cams = cp.path_cameras("orbit", 16, _capture(), CENTRE)
    assert [c["name"] for c in cams[:2]] == ["path_0000", "path_0001"] and len(cams) == 16
    eyes = np.array([c["to_world"][:3, 3] for c in cams]) - CENTRE
    assert np.allclose(np.linalg.norm(eyes, axis=1), 4.0)
    assert np.allclose(np.degrees(np.arcsin(eyes[:, 2] / 4.0)), 30.0)
    az = np.unwrap(np.arctan2(eyes[:, 1], eyes[:, 0]))
    assert az[0] == pytest.approx(0.4) and np.allclose(np.diff(az), 2 * np.pi / 16)
    assert all(_looks_at(c["to_world"], CENTRE) for c in cams)
    assert all(abs(np.linalg.det(c["to_world"][:3, :3]) - 1) < 1e-9 for c in cams)
    assert all(c["to_world"][2, 1] > 0 for c in cams)                     # upright: +Y up
    c = cams[0]
    assert (c["width"], c["height"], c["fx"], c["fy"], c["cx"], c["cy"]) == \
        (40, 30, 36.0, 36.0, 18.5, 16.0)
    # --res: the first capture camera's intrinsics rescaled
    c = cp.path_cameras("orbit", 2, _capture(), CENTRE, res=(80, 60))[0]
    assert (c["width"], c["fx"], c["cx"], c["cy"]) == (80, 72.0, 37.0, 32.0)


def test_spiral_swings_height_and_distance():
    cams = cp.path_cameras("spiral", 40, _capture(), CENTRE)
    eyes = np.array([c["to_world"][:3, 3] for c in cams]) - CENTRE
    d = np.linalg.norm(eyes, axis=1)
    el = np.degrees(np.arcsin(eyes[:, 2] / d))
    assert d.max() / d.min() > 1.15 and el.max() - el.min() > 9.0
    assert abs(el.mean() - 30.0) < 1.0 and abs(d.mean() - 4.0) < 0.05
    assert all(_looks_at(c["to_world"], CENTRE) for c in cams)


def test_path_centre_defaults_to_where_the_capture_looks():
    cams = cp.path_cameras("orbit", 4, _capture())
    assert all(_looks_at(c["to_world"], CENTRE) for c in cams)
    assert np.allclose(cp.axes_centre(_capture()), CENTRE)


def _transforms(path, n, **top):
    frames = [{"file_path": f"./x/{i}", "transform_matrix":
               (cp.look_at([3, i, 1.0], [0, 0, 0]) @ np.linalg.inv(MITSUBA_FROM_OPENGL)).tolist()}
              for i in range(n)]
    path.write_text(json.dumps({**top, "frames": frames}))
    return path


def test_frames_of_different_sizes_refused_before_rendering(tmp_path):
    from comgs_dr.stages.render_comp import _check_frame_sizes
    cams = [comp_folder.camera("a", np.eye(4), 8, 8, 8, 8, 4, 4),
            comp_folder.camera("b", np.eye(4), 16, 8, 8, 8, 4, 4)]
    with pytest.raises(ValueError, match="frame b is 16×8, the first frame 8×8: one size"):
        _check_frame_sizes(cams)


def test_path_file(tmp_path):
    p = _transforms(tmp_path / "p.json", 3, fl_x=30.0, fl_y=25.0, cx=15.0, cy=11.0, w=32, h=24)
    cams = cp.path_cameras(p, None, _capture())
    assert [c["name"] for c in cams] == ["path_0000", "path_0001", "path_0002"]
    assert (cams[1]["fx"], cams[1]["fy"], cams[1]["cx"], cams[1]["width"]) == (30.0, 25.0, 15.0, 32)
    assert np.allclose(cams[2]["to_world"], cp.look_at([3, 2, 1.0], [0, 0, 0]))
    # no size in the file: the capture's (or --res)
    q = _transforms(tmp_path / "q.json", 2, camera_angle_x=1.0)
    assert cp.path_cameras(q, 2, _capture())[0]["width"] == 40
    assert cp.path_cameras(q, 2, _capture(), res=16)[0]["height"] == 16
    with pytest.raises(ValueError, match="has 3 frames, --frames 5"):
        cp.path_cameras(p, 5, _capture())


@pytest.mark.parametrize("kw, match", [
    (dict(path="orbit", frames=0), r"frames must be an integer in \[1,"),
    (dict(path="orbit", frames=2.5), "frames must be an integer"),
    (dict(frames=8), "give path"),
    (dict(path="circle"), "path must be orbit, spiral or a transforms .json"),
    (dict(path="nowhere.json"), "camera path file not found: nowhere.json"),
    (dict(path="orbit", video="out.gif"), "video must be an .mp4"),
    (dict(path="orbit", fps=0), r"fps must be in \(0, 240\]"),
])
def test_config_errors(kw, match):
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        RenderCompConfig(**kw).validate()


def _fake_comp(root):
    """A composition manifest with no object (what the path errors need; nothing rendered)."""
    root.mkdir()
    (root / "composition.json").write_text(json.dumps(
        {"version": 1, "scene": {"ply": "scene.ply"}, "objects": {}, "shadow_probes": "s.npz"}))
    return root


@pytest.mark.parametrize("content, match", [
    ("{not json", "not valid UTF-8 JSON"),
    ('{"frames": []}', "'frames' must be a non-empty list"),
    ('{"camera_angle_x": 0.7, "frames": [{"file_path": "a"}]}', "transform_matrix"),
    ('{"fl_x": -1, "w": 8, "h": 8, "frames": [{"file_path": "a", "transform_matrix": '
     '[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}', "invalid intrinsics"),
])
def test_cli_bad_path_file_exits_2_naming_it(tmp_path, capsys, content, match):
    from comgs_dr.cli import main
    comp = _fake_comp(tmp_path / "comp")
    bad = tmp_path / "bad.json"
    bad.write_text(content)
    cams = _transforms(tmp_path / "cams.json", 2, camera_angle_x=0.8, w=8, h=8)
    capsys.readouterr()
    assert main(["render-comp", str(comp), "--cameras", str(cams), "--path", str(bad),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "bad.json" in err and match in err
    assert "Traceback" not in err


@pytest.mark.parametrize("args, match", [
    (["--path", "orbit", "--frames", "0"], "frames must be an integer"),
    (["--frames", "4"], "give path"),
    ([], "give --cameras"),
    (["--path", "orbit", "--gt-dir", "x"], "no ground truth"),
])
def test_cli_path_errors_exit_2(tmp_path, capsys, args, match):
    from comgs_dr.cli import main
    comp = _fake_comp(tmp_path / "comp")
    cams = [] if args == [] else ["--cameras", str(_transforms(tmp_path / "c.json", 2,
                                                               camera_angle_x=0.8, w=8, h=8))]
    capsys.readouterr()
    assert main(["render-comp", str(comp), *cams, *args, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err


@pytest.fixture(scope="module")
def tiny_comp(tmp_path_factory):
    """A one-object composition (the compose stage on a plane and a ball) + its capture."""
    from test_composite import tiny_composition
    return tiny_composition(tmp_path_factory.mktemp("comp"), 16)


def test_render_comp_orbit_end_to_end(tiny_comp):
    """--path orbit without --cameras (the scene run's dataset places it), --video."""
    import imageio.v2 as imageio
    from PIL import Image

    from comgs_dr.cli import main
    comp, video = tiny_comp / "comp", tiny_comp / "out" / "orbit.mp4"
    assert main(["render-comp", str(comp), "--path", "orbit", "--frames", "4", "--res", "17",
                 "15", "--rays", "4", "--video", str(video), "--fps", "8", "--quiet"]) == 0
    for i in range(4):
        assert np.asarray(Image.open(comp / "renders" / "sop" / f"path_{i:04d}.png")).shape \
            == (15, 17, 3)
    assert video.stat().st_size > 0
    r = imageio.get_reader(str(video))
    frames = [f for f in r]
    assert len(frames) == 4 and frames[0].shape[:2] == (16, 18)     # padded to even sizes
    assert r.get_meta_data()["fps"] == pytest.approx(8.0)
    assert not (comp / "metrics_sop.json").exists()
    s = json.loads((comp / "path_sop.json").read_text())
    assert s["video"] == str(video) and s["video_bytes"] == video.stat().st_size
    assert s["path"] == "orbit" and s["frames"] == 4 and s["resolution"] == [17, 15]


def test_render_comp_summary_and_anisotropic_file_path(tiny_comp):
    """A path file with fx ≠ fy and per-frame principal points renders (comgs_pinhole
    sensor per frame); the summary says why there are no metrics."""
    from comgs_dr.stages.render_comp import render_comp, summary_line
    comp = tiny_comp / "comp"
    frames = [{"file_path": f"./p/{i}", "cx": 6.0 + i, "transform_matrix":
               (cp.look_at([2.5 * np.cos(i), 2.5 * np.sin(i), 1.5], [0.2, 0, 0.3])
                @ np.linalg.inv(MITSUBA_FROM_OPENGL)).tolist()} for i in range(3)]
    p = tiny_comp / "path.json"
    p.write_text(json.dumps({"fl_x": 14.0, "fl_y": 11.0, "cy": 7.0, "w": 16, "h": 12,
                             "frames": frames}))
    s = render_comp(comp, None, "noshadow", rays=4, progress=False, path=p)
    assert s["frames"] == 3 and s["resolution"] == [16, 12] and s["cameras"] is None
    assert s["metrics"] == "skipped: path frames have no ground truth" and "psnr" not in s
    assert "no ground truth: no metrics" in summary_line(s)
    assert json.loads((comp / "path_noshadow.json").read_text())["frames"] == 3
    from PIL import Image
    img = np.asarray(Image.open(comp / "renders" / "noshadow" / "path_0002.png"))
    assert img.shape == (12, 16, 3) and img.std() > 0


def test_per_frame_intrinsics_in_a_sequence_render_as_alone(tiny_comp):
    """Square-pixel frames with their own focal length and principal point move the one
    perspective sensor (pose, fov, principal point): a frame rendered after others is the
    frame rendered alone."""
    from PIL import Image

    from comgs_dr.stages.render_comp import render_comp
    comp = tiny_comp / "comp"
    frames = [{"file_path": f"./p/{i}", "fl_x": 12.0 + 2 * i, "fl_y": 12.0 + 2 * i,
               "cx": 6.0 + 2 * i, "cy": 7.0 - i, "transform_matrix":
               (cp.look_at([2.5 * np.cos(i), 2.5 * np.sin(i), 1.5], [0.2, 0, 0.3])
                @ np.linalg.inv(MITSUBA_FROM_OPENGL)).tolist()} for i in range(3)]
    for name, fr in (("all.json", frames), ("last.json", frames[2:])):
        (tiny_comp / name).write_text(json.dumps({"w": 16, "h": 12, "frames": fr}))
    render_comp(comp, None, "noshadow", rays=4, progress=False, path=tiny_comp / "all.json",
                seed=0)
    seq = np.asarray(Image.open(comp / "renders" / "noshadow" / "path_0002.png"))
    render_comp(comp, None, "noshadow", rays=4, progress=False, path=tiny_comp / "last.json",
                seed=2)
    alone = np.asarray(Image.open(comp / "renders" / "noshadow" / "path_0000.png"))
    assert seq.std() > 0
    np.testing.assert_array_equal(seq, alone)
