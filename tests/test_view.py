"""``comgs view`` without a browser: ``view.session.ViewSession`` (move an object: the edit
re-runs for it only; transform.json; the new frame differs where the object moved) and the
viser app driven through its server-side API (``view.app.ViewerApp``)."""
import json
import socket
import time
from types import SimpleNamespace

import numpy as np
import pytest

from comgs_dr.view.session import (ViewConfig, ViewSession, camera_pose_cv, rotation_wxyz,
                                   viewer_camera, wxyz_rotation)

A0, B0 = np.array([0.6, 0.0, 0.3]), np.array([-0.6, 0.0, 0.3])


def make_two_ball_comp(root):
    """A composition (``stages.compose`` on a plane and two balls ``a``, ``b``, lit by one
    map) in ``root/comp``; returns that folder."""
    from test_composite import object_run, scene_run, sun_map

    from comgs_dr.core.similarity import Similarity, write_placements
    from comgs_dr.lighting import envmap as em
    from comgs_dr.sops import occlusion as occ
    from comgs_dr.stages.compose import ComposeConfig, compose
    run = scene_run(root, 16, 24)
    objects = {name: object_run(root / name, 0.25, albedo, 30)
               for name, albedo in (("a", (0.8, 0.2, 0.2)), ("b", (0.2, 0.3, 0.8)))}
    em.write_exr(root / "env.exr", sun_map(16), "octahedral")
    write_placements(root / "t.json", {"a": Similarity(1.0, np.eye(3), A0),
                                       "b": Similarity(1.0, np.eye(3), B0)})
    cfg = ComposeConfig(shadow=occ.ShadowConfig(count=60, res=8, supersample=1),
                        scene_views=4, min_consistent=1)
    compose(run, objects, root / "t.json", root / "comp", env=root / "env.exr", cfg=cfg,
            progress=False)
    return root / "comp"


@pytest.fixture(scope="module")
def comp(tmp_path_factory):
    return make_two_ball_comp(tmp_path_factory.mktemp("view"))


def _camera(res=48):
    """A camera looking down at both balls from the front."""
    eye, target = np.array([0.0, -3.2, 2.2]), np.array([0.0, 0.0, 0.2])
    f = (target - eye) / np.linalg.norm(target - eye)
    r = np.cross(f, [0, 0, 1.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)                                    # OpenCV: y down
    return viewer_camera(eye, rotation_wxyz(np.stack([r, d, f], 1)), np.radians(45), res, res)


def _pixel(cam, p):
    """(column, row) of world point ``p`` in camera dict ``cam``."""
    m = np.asarray(cam["to_world"])
    x, y, z = m[:3, :3].T @ (np.asarray(p) - m[:3, 3])
    return cam["cx"] - cam["fx"] * x / z, cam["cy"] - cam["fy"] * y / z


def test_viewer_camera_round_trip_and_orientation():
    cam = _camera(40)
    p, q, fov = camera_pose_cv(cam)
    back = viewer_camera(p, q, fov, 40, 40)
    assert np.allclose(back["to_world"], cam["to_world"], atol=1e-9)
    assert fov == pytest.approx(np.radians(45))
    # the target projects to the centre; +X of the world (right of this camera) to the right
    u, v = _pixel(cam, [0, 0, 0.2])
    assert (u, v) == (pytest.approx(20), pytest.approx(20))
    assert _pixel(cam, [0.5, 0, 0.2])[0] > 20 and _pixel(cam, [0, 0, 0.8])[1] < 20
    r = wxyz_rotation(rotation_wxyz(np.diag([1.0, -1.0, -1.0])))
    assert np.allclose(r, np.diag([1.0, -1.0, -1.0]))


def test_move_reruns_the_edit_for_that_object_only(comp, tmp_path):
    import shutil
    c = tmp_path / "comp"
    shutil.copytree(comp, c)
    s = ViewSession(c, ViewConfig(res=48, rays=8))
    env_b = (c / "env" / "b.exr").read_bytes()
    cam = _camera(48)
    before = s.render(cam)
    m = s.world["a"].matrix.copy()
    m[:3, 3] += [0.0, 0.5, 0.0]
    e = s.move("a", m)
    # every re-traced pair involves a; the pairs of b alone come from the cache
    assert e["traced"] and all("_a" in n.split("occ_")[1] for n in e["traced"] + e["culled"])
    assert "occ_region_b__b" in e["reused"]
    assert "own_b" not in e["recomputed"] and "own_a" in e["recomputed"]
    assert json.loads((c / "edit.json").read_text())["pairs"]["reused"] == e["reused"]
    assert (c / "env" / "b.exr").read_bytes() == env_b
    placed = json.loads((c / "composition.json").read_text())["objects"]
    assert np.allclose(np.asarray(placed["a"]["placement"])[:3, 3], A0 + [0, 0.5, 0])
    assert np.allclose(np.asarray(placed["b"]["placement"])[:3, 3], B0)
    # transform.json: written on save only, in the dataset's frame
    assert not (c / "transform.json").exists()
    t = json.loads(s.save().read_text())
    W = np.asarray(json.loads((c / "composition.json").read_text())["world_from_source"])
    for name, want in (("a", A0 + [0, 0.5, 0]), ("b", B0)):
        got = W @ np.asarray(t[name]["transform"]).reshape(4, 4)
        assert np.allclose(got[:3, 3], want, atol=1e-9)
    # the new frame differs where a was and where it is, not around b
    after = s.render(cam)
    diff = np.abs(after - before).max(-1)
    for p in (A0, A0 + [0, 0.5, 0]):
        u, v = _pixel(cam, p)
        assert diff[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2].max() > 0.1
    ub, vb = _pixel(cam, B0)
    assert diff[int(vb) - 2:int(vb) + 3, int(ub) - 2:int(ub) + 3].max() < 0.02
    # another session on the folder starts from the moved placement
    s2 = ViewSession(c, ViewConfig())
    assert np.allclose(s2.world["a"].translation, A0 + [0, 0.5, 0])


def test_view_config_and_cli_errors(comp, capsys):
    from comgs_dr.cli import main
    with pytest.raises(ValueError, match="variant"):
        ViewConfig(variant="fancy").validate()
    with pytest.raises(ValueError, match="res"):
        ViewConfig(res=0).validate()
    with pytest.raises(ValueError, match="pano"):
        ViewConfig(pano=255).validate()
    assert main(["view", str(comp), "--res", "0"]) == 2
    assert "res must be" in capsys.readouterr().err
    assert main(["view", str(comp.parent / "nothing")]) == 2
    assert "composition.json" in capsys.readouterr().err
    with pytest.raises(ValueError, match="no object"):
        ViewSession(comp, ViewConfig()).move("c", np.eye(4))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_viewer_app_moves_an_object_on_gizmo_release(comp, tmp_path):
    """The viser app through its server-side API: a gizmo's release moves the object and
    shows a new composite; drags do not; save writes transform.json."""
    import shutil

    from comgs_dr.view.app import ViewerApp
    c = tmp_path / "comp"
    shutil.copytree(comp, c)
    app = ViewerApp(ViewSession(c, ViewConfig(port=_free_port(), res=32, rays=4)),
                    say=lambda *_: None)
    try:
        assert app.wait_idle(300)
        first = np.array(app.image.image)
        g = app.gizmos["a"]
        g.position = tuple(A0 + [0.0, 0.5, 0.0])
        app._on_gizmo("a", SimpleNamespace(phase="update", client=None))
        time.sleep(0.2)
        assert app.wait_idle(300) and app.session.moves == 0         # dragging: no edit
        app._on_gizmo("a", SimpleNamespace(phase="end", client=None))
        assert app.wait_idle(300) and app.session.moves == 1
        assert not np.array_equal(np.array(app.image.image), first)
        assert "**a** moved" in app.status.content and "from release" in app.status.content
        recs = [json.loads(x) for x in (c / "view" / "log.jsonl").read_text().splitlines()]
        assert recs[-1]["why"] == "moved a" and recs[-1]["total_s"] > 0
        assert np.allclose(app.positions["a"].value, A0 + [0, 0.5, 0])
        app.variant.value = "paste"
        app.worker.submit("save", app._save)
        app.worker.submit("full", lambda: app._render_full(None))
        assert app.wait_idle(300)
        t = json.loads((c / "transform.json").read_text())
        assert np.allclose(np.asarray(t["a"]["transform"]).reshape(4, 4)[:3, 3],
                           A0 + [0, 0.5, 0])
        assert list((c / "view").glob("full_*.png"))
    finally:
        app.stop()


def test_move_estimates_the_light_of_the_moved_object_only(tmp_path):
    """A composition whose light was estimated: a move estimates the moved object's light
    at its new centre (``estimate_light``, its files in env/<name>_estimate/) and keeps
    the other's map byte for byte."""
    from test_composite import object_run, scene_run

    from comgs_dr.core.similarity import Similarity, write_placements
    from comgs_dr.sops import occlusion as occ
    from comgs_dr.stages.compose import ComposeConfig, compose
    run = scene_run(tmp_path, 16, 24)
    object_run(tmp_path / "o", 0.25, (0.8, 0.2, 0.2), 30)
    write_placements(tmp_path / "t.json", {"a": Similarity(1.0, np.eye(3), A0),
                                           "b": Similarity(1.0, np.eye(3), B0)})
    sky = lambda pos, name: np.full((16, 32, 3), 0.5)                       # noqa: E731
    cfg = ComposeConfig(shadow=occ.ShadowConfig(count=30, res=8, supersample=1),
                        scene_views=4, min_consistent=1, env_res=32)
    c = tmp_path / "comp"
    compose(run, {"a": tmp_path / "o", "b": tmp_path / "o"}, tmp_path / "t.json", c,
            estimator=sky, cfg=cfg, progress=False)
    env_a, env_b = (c / "env" / "a.exr").read_bytes(), (c / "env" / "b.exr").read_bytes()
    s = ViewSession(c, ViewConfig(pano=32, label="outdoor"))
    assert s.env is None
    m = s.world["a"].matrix.copy()
    m[:3, 3] += [0.0, 0.4, 0.0]
    e = s.move("a", m)
    assert e["lighting"] > 0
    assert (c / "env" / "b.exr").read_bytes() == env_b
    assert (c / "env" / "a.exr").read_bytes() != env_a
    assert (c / "env" / "a_estimate" / "a.json").is_file()
    assert not (c / "env" / "b_estimate").exists()
    at = json.loads((c / "composition.json").read_text())["lighting"]["estimated_at"]
    assert np.allclose(at["a"], A0 + [0, 0.4, 0], atol=0.05)
