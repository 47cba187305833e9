"""Cutting an object out of its own capture (``comgs cut``, stages.cut_object, surfels.cut).

The scene: surfels of a textured, slightly noisy 3×3 floor with a sphere and an open-bottom
box standing on it, a low "sheet" bump lying against the box, all turned and moved by a
rigid transform (so the plane is not z = 0), photographed by a ring of cameras looking at
the objects. Checks the plane, the kept share of the objects, the floor left in the cut,
the measures, the box option, the masks and the error exits."""
import argparse
import json

import numpy as np
import pytest

from comgs_dr.cli.cut import _add_cut
from comgs_dr.stages import cut_object as co

SPHERE_C, SPHERE_R = np.array([0.33, 0.05, 0.25]), 0.25
BOX_LO, BOX_HI = np.array([-0.45, -0.15, 0.0]), np.array([-0.15, 0.15, 0.4])
N_CAMS, RES = 12, (48, 36)


def _world():
    """A fixed rotation (about a tilted axis) and translation of the whole scene."""
    axis = np.array([0.3, -0.5, 0.8])
    axis /= np.linalg.norm(axis)
    a = np.radians(37.0)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    r = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, [0.7, -1.2, 2.5]
    return m


def _parts(seed=0, floor=True, objects=True, sheet=True):
    """{label: SurfelParams} before the world transform (z up, floor at z = 0)."""
    import trimesh

    from comgs_dr.surfels.from_mesh import from_mesh
    rng = np.random.default_rng(seed)
    out = {}
    if floor:
        f = trimesh.Trimesh([[-1.5, -1.5, 0], [1.5, -1.5, 0], [1.5, 1.5, 0], [-1.5, 1.5, 0]],
                            [[0, 1, 2], [0, 2, 3]])
        d = from_mesh(f, 9000, seed=seed, opacity=0.95).to_numpy()
        d["means"][:, 2] += rng.normal(0, 0.002, len(d["means"]))      # reconstruction noise
        d["sh"][:, 0] += rng.uniform(-0.8, 0.8, (len(d["sh"]), 3))        # texture
        out["floor"] = d
    if sheet:                                       # a low bump lying against the box's -y wall
        u, v = np.meshgrid(np.linspace(-0.5, -0.1, 25), np.linspace(-0.42, -0.16, 17))
        z = 0.04 * np.exp(-((u + 0.3) ** 2 + (v + 0.21) ** 2) / (2 * 0.06 ** 2))
        verts = np.stack([u.ravel(), v.ravel(), z.ravel()], 1)
        faces = [[i * 25 + j, i * 25 + j + 1, (i + 1) * 25 + j + 1] for i in range(16) for j in range(24)]
        faces += [[i * 25 + j, (i + 1) * 25 + j + 1, (i + 1) * 25 + j] for i in range(16) for j in range(24)]
        out["sheet"] = from_mesh(trimesh.Trimesh(verts, faces), 700, seed=seed + 1,
                                 opacity=0.95).to_numpy()
    if objects:
        s = trimesh.creation.icosphere(3, SPHERE_R).apply_translation(SPHERE_C)
        out["sphere"] = from_mesh(s, 4000, seed=seed + 2, opacity=0.95).to_numpy()
        b = trimesh.creation.box(extents=BOX_HI - BOX_LO).apply_translation((BOX_LO + BOX_HI) / 2)
        b.update_faces(b.face_normals[:, 2] > -0.5)                      # no bottom face
        out["box"] = from_mesh(b, 3000, seed=seed + 3, opacity=0.95).to_numpy()
    return out


def _transform(parts, m):
    from comgs_dr.core.similarity import Similarity
    from comgs_dr.surfels.params import SurfelParams
    from comgs_dr.surfels.transform import transform_surfels
    sim = Similarity(1.0, m[:3, :3], m[:3, 3])
    labels = np.concatenate([[k] * len(d["means"]) for k, d in parts.items()])
    ps = [transform_surfels(SurfelParams.from_numpy(**d), sim) for d in parts.values()]
    return SurfelParams.concat(ps), labels


def _ring(m, forward_facing=False):
    """Camera-to-world (OpenGL, NeRF layout) matrices: a ring looking at the objects, or a
    forward-facing row in front of a wall at x = 0 (looking along -x)."""
    rng = np.random.default_rng(5)
    mats = []
    for i in range(N_CAMS):
        if forward_facing:
            o, t, up = [2.0, -0.6 + 0.1 * i, 1.0], [0.0, 0.0, 1.0 + 0.05 * np.sin(i)], [0, 0, 1]
        else:
            a = 2 * np.pi * i / N_CAMS
            o = [2.2 * np.cos(a), 2.2 * np.sin(a), 1.3 + 0.2 * np.sin(3 * a)]
            t, up = np.array([0.0, 0.0, 0.2]) + rng.normal(0, 0.04, 3), [0, 0, 1]
        tw = _look_at(np.array(o, float), np.array(t, float), np.array(up, float))
        mats.append(m @ tw @ np.diag([-1.0, 1, -1, 1]))                 # Mitsuba -> OpenGL
    return mats


def _look_at(o, t, up):
    """Mitsuba camera-to-world: +Z forward, +Y up, +X left."""
    z = (t - o) / np.linalg.norm(t - o)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], 1)
    m[:3, 3] = o
    return m


def _write_case(root, parts, m, forward_facing=False, masks=False):
    """A NeRF-layout dataset (tiny images) + a step-1 run folder; returns (run, data)."""
    from PIL import Image

    from comgs_dr.surfels.io import save_ply
    from comgs_dr.train.run import write_run_info
    data, run = root / "data", root / "run"
    (data / "images").mkdir(parents=True)
    frames = []
    for i, c2w in enumerate(_ring(m, forward_facing)):
        img = np.full((RES[1], RES[0], 3), 40 + 10 * i, np.uint8)
        Image.fromarray(img).save(data / "images" / f"v{i:02d}.png")
        frames.append({"file_path": f"images/v{i:02d}", "transform_matrix": c2w.tolist()})
        if masks:
            (data / "masks").mkdir(exist_ok=True)
            mk = np.zeros((RES[1], RES[0]), np.uint8)
            mk[10:20, 15 + i:30] = 255
            Image.fromarray(mk).save(data / "masks" / f"v{i:02d}.png")
    (data / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": np.radians(50.0), "frames": frames}))
    params, labels = _transform(parts, m)
    write_run_info(run, data, "scene", 1, False)
    save_ply(params, run / "point_cloud.ply")
    return run, data, labels


def _cli(argv) -> int:
    """``comgs cut ...`` through the command's own parser (as ``comgs_dr.cli.main`` runs it)."""
    p = argparse.ArgumentParser(prog="comgs")
    _add_cut(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(["cut", *argv, "--quiet"])
    return args.func(args)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    m = _world()
    run, data, labels = _write_case(tmp_path_factory.mktemp("cut"), _parts(), m)
    return {"m": m, "run": run, "data": data, "labels": labels,
            "root": tmp_path_factory.mktemp("cut_out")}


def _phases(scene, cfg=None):
    cfg = cfg or co.CutConfig()
    src = co.load_source(scene["run"])
    look = co.find_look_at(src)
    plane = co.fit_plane(src, look, cfg)
    sel = co.select(src, look, plane, cfg)
    return src, look, plane, sel


def test_plane_look_at_and_the_grown_object(scene):
    src, look, plane, sel = _phases(scene)
    m, labels, keep = scene["m"], scene["labels"], sel["keep"]
    n_true = m[:3, :3] @ [0, 0, 1.0]
    assert np.degrees(np.arccos(np.clip(plane.normal @ n_true, -1, 1))) < 0.5
    assert plane.offset == pytest.approx(-n_true @ m[:3, 3], abs=2e-3)
    # the cameras aim at (0, 0, 0.2) ± 4 cm
    assert np.linalg.norm(look["point"] - (m[:3, :3] @ [0, 0, 0.2] + m[:3, 3])) < 0.06
    obj = np.isin(labels, ["sphere", "box"])
    assert keep[obj].mean() >= 0.98, keep[obj].mean()
    floorish = np.isin(labels, ["floor", "sheet"])
    assert (keep & floorish).sum() / keep.sum() < 0.01
    assert (keep & (labels == "sheet")).sum() < 0.1 * (labels == "sheet").sum()
    meas = co.measure(src, plane, keep, look, co.CutConfig())
    own = co.measure(src, plane, obj, look, co.CutConfig())      # the objects' own low parts
    assert meas["below_share"] < 1e-3
    assert meas["flat_slab_share"] - own["flat_slab_share"] < 0.005
    assert meas["slab_share"] - own["slab_share"] < 0.01


def test_cli_writes_the_object_run_in_the_plane_frame(scene):
    from comgs_dr.data.load import load_dataset
    from comgs_dr.surfels.io import load_ply
    out = scene["root"] / "grow"
    assert _cli([str(scene["run"]), "--out", str(out)]) == 0
    s = json.loads((out / "cut.json").read_text())
    assert s["measures"]["below_share"] < 1e-3 and s["selection"]["method"] == "grow"
    x = np.asarray(load_ply(out / "point_cloud.ply").means).T              # [K, 3]
    assert x[:, 2].min() > 0 and x[:, 2].max() == pytest.approx(0.5, abs=0.02)  # sphere top
    assert np.abs(np.percentile(x[:, :2], [0.5, 99.5], 0).sum(0)).max() < 0.02  # centred
    back = x @ np.array(s["world_from_object"])[:3, :3].T + np.array(s["world_from_object"])[:3, 3]
    src = np.asarray(load_ply(scene["run"] / "point_cloud.ply").means).T
    from scipy.spatial import cKDTree
    assert cKDTree(src).query(back)[0].max() < 1e-4
    # the object run's cameras are the capture's, moved into the object frame
    cams = load_dataset(out / "data", pixels=False)
    assert len(cams.train) + len(cams.test) == N_CAMS
    c_obj = np.array([v.camera.center for v in cams.train])
    assert np.all(c_obj[:, 2] > 1.0)                                      # above the plane


def test_box_option_and_the_floor_it_lets_in(scene):
    out = scene["root"] / "box"
    box = ["-0.7", "-0.7", "-0.1", "0.7", "0.7", "0.8"]
    assert _cli([str(scene["run"]), "--out", str(out), "--box-frame", "plane",
                 "--object-box", *box]) == 0
    s = json.loads((out / "cut.json").read_text())["measures"]
    assert s["below_share"] > 0.1 and s["flat_slab_share"] > 0.1     # the floor is measured
    cfg = co.CutConfig(object_box=(-0.7, -0.7, 0.012, 0.7, 0.7, 0.8), box_frame="plane")
    src, look, plane, sel = _phases(scene, cfg)
    obj = np.isin(scene["labels"], ["sphere", "box"])
    assert sel["keep"][obj].mean() > 0.97 and not sel["keep"][scene["labels"] == "floor"].any()
    assert co.measure(src, plane, sel["keep"], look, cfg)["below_share"] == 0.0


def test_masks_rendered_and_given(scene, tmp_path):
    from comgs_dr.data.images import read_image, read_mask
    out = scene["root"] / "masks"
    assert _cli([str(scene["run"]), "--out", str(out), "--masks"]) == 0
    s = json.loads((out / "cut.json").read_text())
    assert s["masks"]["rendered"] == N_CAMS and s["masks"]["given"] == 0
    for i in (0, 5):
        mk = read_mask(out / "masks" / f"images/v{i:02d}.png")
        assert mk.shape == (RES[1], RES[0])
        assert mk[RES[1] // 2, RES[0] // 2] > 0.9 and mk[1, 1] < 0.05   # object centre / floor
        rgba = read_image(out / "data" / "images" / f"images/v{i:02d}.png")
        assert rgba.shape[2] == 4 and np.allclose(rgba[..., 3], mk, atol=1 / 255)
    # a dataset with its own masks: used as they are, not rendered
    run, data, _ = _write_case(tmp_path, _parts(), scene["m"], masks=True)
    out2 = tmp_path / "out"
    assert _cli([str(run), "--out", str(out2), "--masks"]) == 0
    s = json.loads((out2 / "cut.json").read_text())
    assert s["masks"] == pytest.approx({**s["masks"], "given": N_CAMS, "rendered": 0})
    assert (out2 / "masks" / "images/v03.png").read_bytes() == (data / "masks" / "v03.png").read_bytes()


def test_errors_exit_2_and_name_the_problem(scene, tmp_path, capsys):
    m = _world()
    # a floor with nothing on it
    run, _, _ = _write_case(tmp_path / "floor", _parts(objects=False, sheet=False), m)
    assert _cli([str(run), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err
    assert "nothing above the plane near the look-at point" in err and "point_cloud.ply" in err
    # a wall photographed head-on: no plane under the cameras' look-at point
    wall = _parts(floor=True, objects=False, sheet=False)
    d = wall["floor"]
    d["means"] = d["means"][:, [2, 0, 1]] + [0, 0, 1.0]                   # the floor stood up
    run, _, _ = _write_case(tmp_path / "wall", {"floor": d}, m, forward_facing=True)
    assert _cli([str(run), "--out", str(tmp_path / "o2")]) == 2
    assert "no support plane found" in capsys.readouterr().err
    # a box that holds nothing
    assert _cli([str(scene["run"]), "--out", str(tmp_path / "o3"),
                 "--object-box", "50", "50", "50", "51", "51", "51"]) == 2
    err = capsys.readouterr().err
    assert "holds no surfel" in err and "the surfels span" in err
    # bad values and missing runs
    assert _cli([str(scene["run"]), "--out", str(tmp_path / "o4"), "--min-height", "0.5"]) == 2
    assert "min_height" in capsys.readouterr().err
    assert _cli([str(tmp_path / "nope"), "--out", str(tmp_path / "o5")]) == 2
    assert "run.json not found" in capsys.readouterr().err


def test_through_comgs_main(scene, tmp_path, monkeypatch, capsys):
    """``comgs_dr.cli.main`` (registered there, or added here until it is) exits 2 the same
    way, its numeric checks apply to the box, and the help lists the flags."""
    from comgs_dr import cli
    if not any(getattr(f, "__name__", "") == "_add_cut" for f in cli._SUBCOMMANDS):
        monkeypatch.setattr(cli, "_SUBCOMMANDS", cli._SUBCOMMANDS + (_add_cut,))
    assert cli.main(["cut", str(scene["run"]), "--out", str(tmp_path / "o"), "--object-box",
                     "50", "50", "50", "51", "51", "51", "--quiet"]) == 2
    assert "holds no surfel" in capsys.readouterr().err
    assert cli.main(["cut", str(scene["run"]), "--out", str(tmp_path / "o"), "--object-box",
                     "0", "0", "0", "1", "1", "nan"]) == 2
    assert "--object-box" in capsys.readouterr().err
    assert cli.main(["cut", "--help"]) == 0
    h = capsys.readouterr().out
    assert all(f in h for f in ("--masks", "--grow-radius", "--plane-tolerance", "--data"))
