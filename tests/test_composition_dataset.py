"""Composition ground truth (comgs_dr.data.composition_dataset, `comgs make-dataset composition`).

One tiny dataset (32 px, 3 views per split, 4 spp) of the shared meshes and maps is rendered
once per module; the checks trace their own rays against the recorded geometry (meshes at
``mesh_to_world``, props, ground) to predict object pixels and sun shadows independently.
"""
import json

import mitsuba as mi
import numpy as np
import pytest
from PIL import Image

from comgs_dr import cli
from comgs_dr.core.colorspace import srgb_decode
from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.similarity import read_placements
from comgs_dr.data import composition_dataset as cd
from comgs_dr.data import synthetic_io as sio
from comgs_dr.data.load import load_dataset
from comgs_dr.data.synthetic import ENVMAP_TO_WORLD, shared_data_dir

RES, VIEWS = 32, 3
needs_shared = pytest.mark.skipif(
    not all((shared_data_dir() / o["mesh"]).is_file() for o in cd.SHARED_OBJECTS.values())
    or not (shared_data_dir() / "hdri" / cd.CompositionDatasetConfig.scene_map).is_file(),
    reason=f"shared sample data not found at {shared_data_dir()} (set $COMGS_DATA_DIR)")


@pytest.fixture(scope="module")
def ds(tmp_path_factory, variant):
    out = tmp_path_factory.mktemp("comp")
    summary = cd.make_composition_dataset(cd.CompositionDatasetConfig(
        out_dir=out, resolution=RES, scene_views=VIEWS, object_views=VIEWS, test_views=VIEWS,
        spp=4, sfm_points=300), progress=False)
    return out, summary, json.loads((out / "composition.json").read_text())


def _png(path):
    return np.asarray(Image.open(path), np.float32) / 255.0


def _erode(m):
    """Pixels whose 8 neighbours are set too (away from class borders)."""
    p = np.pad(m, 1)
    return np.all([p[1 + dy:1 + dy + m.shape[0], 1 + dx:1 + dx + m.shape[1]]
                   for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)


def _trace(scene, o, d):
    """First hits: t [N], index into scene.shapes() [N] (-1: none), normals [N, 3]."""
    si = scene.ray_intersect(mi.Ray3f(to_jit(mi.Point3f, o.T),
                                      to_jit(mi.Vector3f, d.T)))
    idx = np.full(len(d), -1)
    for k, s in enumerate(scene.shapes()):
        idx[np.array(si.shape == mi.ShapePtr(s), bool)] = k
    return np.array(si.t), idx, np.array(si.n).T


def _classes(comp, frame, angle_x):
    """Per pixel (from transform_matrix alone): object seen, ground/prop point in an
    object's sun shadow, point lit by the sun and > 1 unit from every object's box."""
    T = mi.ScalarTransform4f
    d = {"type": "scene"}
    for k, sh in comp["scene"]["shapes"].items():                      # ground, wall, box
        d[k] = {"type": sh["type"], "to_world": T(sh["to_world"])}
    for n, o in comp["objects"].items():
        d[f"obj_{n}"] = {"type": o["mesh"].rsplit(".", 1)[-1], "filename": o["mesh"],
                         "to_world": T(o["mesh_to_world"])}
    scene = mi.load_dict(d)
    is_obj = np.array([s.id().startswith("obj_") for s in scene.shapes()] + [False])
    m = np.asarray(frame["transform_matrix"])
    t = np.tan(angle_x / 2)
    y, x = np.mgrid[:RES, :RES] + 0.5
    cam = np.stack([(2 * x / RES - 1) * t, -(2 * y / RES - 1) * t, -np.ones_like(x)], -1)
    dirs = cam.reshape(-1, 3) @ m[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)                  # [H*W, 3]
    hit_t, idx, n = _trace(scene, np.broadcast_to(m[:3, 3], dirs.shape), dirs)
    p = m[:3, 3] + np.where(np.isfinite(hit_t), hit_t, 0.0)[:, None] * dirs
    sun = np.asarray(comp["scene"]["sun_direction"])
    n = np.where((n @ sun)[:, None] < 0, -n, n)
    _, sidx, _ = _trace(scene, p + 1e-3 * n, np.broadcast_to(sun, p.shape))
    boxes = np.array([o["bbox_world"] for o in comp["objects"].values()])  # [K, 2, 3]
    gap = np.max(np.maximum(boxes[None, :, 0, :2] - p[:, None, :2],
                            p[:, None, :2] - boxes[None, :, 1, :2]), -1).min(1)
    valid = idx >= 0
    obj = valid & is_obj[idx]
    shadow = valid & ~obj & is_obj[sidx] & (sidx >= 0)
    far = valid & ~obj & (sidx < 0) & (gap > 1.0)
    return [a.reshape(RES, RES) for a in (obj, shadow, far)]


@needs_shared
def test_layout_and_loaders(ds):
    out, summary, comp = ds
    scene = load_dataset(out / "scene")
    assert len(scene.train) == VIEWS and len(scene.test) == VIEWS and scene.points is not None
    assert scene.train[0].mask is None and scene.train[0].image.shape == (RES, RES, 3)
    for name in ("spot", "teapot"):
        obj = load_dataset(out / "objects" / name)
        assert len(obj.train) == VIEWS and obj.train[0].mask is not None
        meta = json.loads((out / "objects" / name / "meta.json").read_text())
        assert meta["envmap"].endswith("blender_studio.exr") and meta["relight_envmaps"] == {}
        assert comp["objects"][name]["object_to_world"] == meta["object"]["object_to_world"]
    assert comp["objects"]["spot"]["material"]["texture"].endswith("spot_texture.png")
    assert comp["objects"]["teapot"]["material"]["base_color"] == [0.8, 0.3, 0.08]
    assert comp["scene"]["envmap"].endswith("blender_sunrise.exr")
    assert set(comp["seconds"]) == {"scene", "objects", "comp", "total"}
    tr = json.loads((out / "comp" / "transforms_test.json").read_text())
    assert 0 < tr["camera_angle_x"] < np.pi and len(tr["frames"]) == VIEWS
    for i, f in enumerate(tr["frames"]):
        assert f["file_path"] == f"./gt/r_{i:03d}" and f["empty_path"] == f"./empty/r_{i:03d}"
        m = np.asarray(f["transform_matrix"])
        assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-6)
        assert np.allclose(np.asarray(f["to_world_mitsuba"]), m @ np.diag([-1.0, 1, -1, 1]))
        for sub in ("gt", "empty"):
            im = Image.open(out / "comp" / sub / f"r_{i:03d}.png")
            assert im.mode == "RGB" and im.size == (RES, RES)
    # spiral: rising elevation, all looking at the recorded centre
    elev = [f["elevation_deg"] for f in tr["frames"]]
    assert elev == sorted(elev) and elev[0] < elev[-1]
    for f in tr["frames"]:
        m = np.asarray(f["transform_matrix"])
        to_c = np.asarray(comp["comp"]["centre"]) - m[:3, 3]
        assert np.dot(-m[:3, 2], to_c / np.linalg.norm(to_c)) > 0.999


@needs_shared
def test_placements_rest_on_ground_side_by_side(ds):
    out, _, comp = ds
    placements = read_placements(out / "transform.json")
    assert list(placements) == ["spot", "teapot"]
    boxes = {}
    for name, p in placements.items():
        o = comp["objects"][name]
        assert np.allclose(p.matrix, o["placement"])
        assert np.allclose(p.rotation[2], [0, 0, 1]) and abs(p.scale - 0.5) < 1e-9   # about Z
        v = sio.load_mesh(o["mesh"])["vertices"]
        w = p.points(v @ np.asarray(o["object_to_world"])[:3, :3].T
                     + np.asarray(o["object_to_world"])[:3, 3])
        assert abs(w[:, 2].min() - comp["scene"]["shapes"]["ground"]["top_z"]) < 1e-4  # touches the ground
        assert np.allclose([w.min(0), w.max(0)], o["bbox_world"], atol=1e-5)
        boxes[name] = w.min(0), w.max(0)
    size = 2 * 0.5                                    # object size: 2 x object_scale
    dist = np.linalg.norm(placements["spot"].translation[:2] - placements["teapot"].translation[:2])
    assert 1.2 * size <= dist <= 2.0 * size
    (a0, a1), (b0, b1) = boxes.values()
    assert np.any(a1[:2] < b0[:2]) or np.any(b1[:2] < a0[:2])      # boxes apart in XY


@needs_shared
def test_sun_direction_follows_the_map_convention(ds):
    _, _, comp = ds
    a = np.array(mi.Bitmap(comp["scene"]["envmap"]))[..., :3]
    lum = a @ [0.2126, 0.7152, 0.0722]
    i, j = np.unravel_index(np.argmax(lum), lum.shape)
    th, phi = np.pi * (i + 0.5) / a.shape[0], np.pi * (1 - 2 * (j + 0.5) / a.shape[1])
    d = [np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)]
    assert np.allclose(comp["scene"]["sun_direction"], d, atol=1e-6)
    assert comp["envmap_orientation"]["to_world_mitsuba"] == ENVMAP_TO_WORLD.tolist()


@needs_shared
def test_composite_has_objects_and_shadows_and_matches_empty_elsewhere(ds):
    out, _, comp = ds
    tr = json.loads((out / "comp" / "transforms_test.json").read_text())
    n_obj = n_shadow = n_far = 0
    obj_diff, far_diff, lum_gt, lum_empty = [], [], 0.0, 0.0
    for f in tr["frames"]:
        gt = _png(out / "comp" / (f["file_path"][2:] + ".png"))
        empty = _png(out / "comp" / (f["empty_path"][2:] + ".png"))
        mask = _png(out / "comp" / f["mask_path"][2:])
        obj, shadow, far = _classes(comp, f, tr["camera_angle_x"])
        inter, union = np.sum(obj & (mask >= 0.5)), np.sum(obj | (mask >= 0.5))
        assert union > 0 and inter / union > 0.7                    # mask = traced objects
        diff = np.abs(gt - empty).mean(-1)
        o, s, fa = _erode(obj), _erode(shadow), _erode(far)
        obj_diff += list(diff[o])
        far_diff += list(diff[fa])
        lum = lambda im: float((srgb_decode(im[s]) @ [0.2126, 0.7152, 0.0722]).sum())  # noqa: E731
        lum_gt, lum_empty = lum_gt + lum(gt), lum_empty + lum(empty)
        n_obj, n_shadow, n_far = n_obj + o.sum(), n_shadow + s.sum(), n_far + fa.sum()
    assert n_obj >= 20 and n_shadow >= 10 and n_far >= 50
    assert np.mean(obj_diff) > 0.05                   # the objects are really in the frame
    assert np.mean(far_diff) < 0.01 and np.percentile(far_diff, 95) < 0.04   # same elsewhere
    assert lum_gt < 0.7 * lum_empty                    # their sun shadows darken the ground


@needs_shared
def test_cli_path_objects_and_summary(tmp_path, capsys):
    mesh = shared_data_dir() / "meshes" / "suzanne.obj"
    code = cli.main(["make-dataset", "composition", "--out", str(tmp_path), "--objects",
                     f"teapot,{mesh}", "--scene-map", "kiara_1_dawn_1k.hdr", "--res", "16",
                     "--comp-res", "24",
                     "--scene-views", "1", "--object-views", "1", "--test-views", "1",
                     "--spp", "2", "--points", "0", "--probe-height", "8", "--quiet"])
    assert code == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "composite test views (24px; captures 16px)" in printed
    assert "2 placement probe(s)" in printed
    from comgs_dr.lighting.envmap import read_envmap_file
    for name in ("teapot", "suzanne"):
        img, layout = read_envmap_file(tmp_path / "probes" / f"{name}.exr")
        assert img.shape == (8, 16, 3) and np.isfinite(img).all() and img.max() > 0
    comp = json.loads((tmp_path / "composition.json").read_text())
    where = json.loads((tmp_path / "probes" / "probes.json").read_text())
    box = np.asarray(comp["objects"]["teapot"]["bbox_world"])
    assert np.allclose(where["teapot"]["position"], box.mean(0))
    assert list(comp["objects"]) == ["teapot", "suzanne"]
    assert comp["objects"]["suzanne"]["material"]["base_color"] == [0.6, 0.6, 0.6]
    assert comp["scene"]["envmap"].endswith("kiara_1_dawn_1k.hdr")
    assert not (tmp_path / "scene" / "points3d.ply").exists()
    assert set(read_placements(tmp_path / "transform.json")) == {"teapot", "suzanne"}


@needs_shared
@pytest.mark.parametrize("flags, message", [
    (["--objects", "dragon"], "unknown object 'dragon'"),
    (["--objects", "spot,spot"], "object names must be distinct"),
    (["--objects", "missing.obj"], "mesh of object 'missing.obj' not found"),
    (["--scene-map", "nowhere.hdr"], "environment map not found"),
    (["--res", "0"], "resolution must be >= 8"),
    (["--test-views", "0"], "test_views must be >= 1"),
    (["--spp", "-2"], "spp must be >= 1"),
    (["--points", "-1"], "sfm_points must be >= 0"),
    (["--probe-height", "-1"], "probe_height must be in [0, 4096]"),
    (["--probe-height", "5000"], "probe_height must be in [0, 4096]"),
])
def test_bad_flags_are_clear_errors(tmp_path, capsys, flags, message):
    out = tmp_path / "o"
    assert cli.main(["make-dataset", "composition", "--out", str(out), *flags]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()                           # refused before writing anything


def test_spacing_too_small_is_refused():
    v = np.array([[-1.0, -1, -1], [1, 1, 1]])
    with pytest.raises(ValueError, match="spacing 1.0 is too small"):
        cd.place_objects({"a": v, "b": v}, 0.0, 0.5, 1.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="object_scale must be > 0"):
        cd.CompositionDatasetConfig(object_scale=0)


@needs_shared
def test_placement_probe_sees_the_sun_and_the_scene(ds):
    """The probe at an object's placement (data.placement_probe), rebuilt from
    composition.json: the sun is its brightest direction; below, it sees the scene's ground
    (lit, so not black), not the map's own lower half."""
    from comgs_dr.core.equirect import equirect_uv_to_dir_np
    from comgs_dr.data import placement_probe as pp
    from comgs_dr.lighting.envmap import read_envmap_file
    from comgs_dr.lighting.hdr import area_resize_equirect
    out, _, comp = ds
    name = next(iter(comp["objects"]))
    tr = read_placements(out / "transform.json")
    assert np.allclose(pp.placement_position(out, name), tr[name].translation)
    probe = pp.placement_probe(out, name, height=16, spp_side=2).astype(np.float64)
    d = equirect_uv_to_dir_np(np.stack(np.meshgrid((np.arange(32) + 0.5) / 32,
                                                      (np.arange(16) + 0.5) / 16), -1).reshape(-1, 2))
    lum = probe.reshape(-1, 3) @ [0.2126, 0.7152, 0.0722]
    assert d[np.argmax(lum)] @ np.asarray(comp["scene"]["sun_direction"]) > np.cos(np.radians(15))
    env = area_resize_equirect(read_envmap_file(comp["scene"]["envmap"])[0].astype(np.float64),
                               16, 32) * comp["scene"]["envmap_scale"]
    down = d[:, 2] < -0.7
    assert lum[down].min() > 0 and np.isfinite(probe).all()
    assert np.abs(probe.reshape(-1, 3)[down] - env.reshape(-1, 3)[down]).mean() > 0.01
    box = np.asarray(comp["objects"][name]["bbox_world"])
    assert np.allclose(pp.placement_position(out, name, at="centre"), box.mean(0))
    with pytest.raises(KeyError, match="no placement"):
        pp.placement_position(out, "nothing")
    with pytest.raises(ValueError, match="'origin' or 'centre'"):
        pp.placement_position(out, name, at="top")
