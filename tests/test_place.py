"""``comgs place`` (stages.place): the pixel's ray into surfels, the base on the hit point, up
along the surface normal (or world up), the lift that clears the surface, the placement file
``compose`` reads, and the errors — against a surfel plane (flat and tilted) and a surfel
sphere made with ``surfels.from_mesh``, seen by 48 px cameras."""
import json
import math

import numpy as np
import pytest

import comgs_dr
from comgs_dr.core.similarity import Similarity, read_placements

trimesh = pytest.importorskip("trimesh")

RES = 48
BOX = (0.4, 0.4, 0.3)            # the object: a surfel box, its bottom at z = 0.1 (own frame)
SPHERE_R = 1.0


@pytest.fixture(scope="module", autouse=True)
def _variant():
    comgs_dr.set_variant("llvm_ad_rgb")


def _look_at(o, t, up=(0.0, 0.0, 1.0)):
    """Mitsuba camera-to-world: +Z forward, +Y up, +X left."""
    o, t, up = (np.asarray(v, float) for v in (o, t, up))
    z = (t - o) / np.linalg.norm(t - o)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    m[:3, 3] = o
    return m


def _camera(o, t):
    from comgs_dr.data.types import Camera
    return Camera(_look_at(o, t), RES, RES, 40.0)


def _rot_x(deg):
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def _plane(tilt_deg=0.0, n=12000):
    """A 4 × 4 surfel quad through the origin, turned ``tilt_deg`` about X; (params, normal)."""
    from comgs_dr.surfels.from_mesh import from_mesh
    r = _rot_x(tilt_deg)
    v = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], float) @ r.T
    mesh = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    return from_mesh(mesh, n, seed=1), r @ [0.0, 0.0, 1.0]


def _sphere(n=20000):
    from comgs_dr.surfels.from_mesh import from_mesh
    return from_mesh(trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_R), n, seed=2)


def _box(n=3000):
    from comgs_dr.surfels.from_mesh import from_mesh
    m = trimesh.creation.box(extents=BOX)
    m.apply_translation([0.3, -0.2, BOX[2] / 2 + 0.1])       # off-centre, lifted: base ≠ 0
    return from_mesh(m, n, seed=3)


@pytest.fixture(scope="module")
def scenes():
    return {"flat": _plane(0.0), "tilted": _plane(20.0), "sphere": _sphere(), "box": _box()}


def _means(params):
    return np.asarray(params.to_numpy()["means"], np.float64)


def _place(scene, obj, cam, px, **cfg):
    from comgs_dr.stages.place import PlaceConfig, pixel_target, place_object
    from comgs_dr.surfels import raycast
    c = PlaceConfig(**cfg)
    trace = raycast.trace_scene(scene)
    target = pixel_target(trace, cam, px[0], px[1], c)
    return place_object(scene, obj, target, c, trace)


def _ray_plane(o, d, n):
    return o + d * (-(o @ n) / (d @ n))


def _ray_sphere(o, d, r=SPHERE_R):
    b = o @ d
    t = -b - math.sqrt(b * b - (o @ o - r * r))
    return o + t * d


def _angle(a, b):
    return math.degrees(math.acos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b),
                                          -1, 1)))


# ----------------------------------------------------------------------------- geometry

def test_pixel_ray_is_the_renderers_ray():
    """The pixel's ray is the one the ``surfel_gbuffer`` integrator traces for that pixel."""
    from comgs_dr.core.cameras import camera_rays
    from comgs_dr.stages.place import pixel_ray
    cam = _camera([0.3, -3.0, 2.0], [0.1, 0.2, 0.0])
    cam.principal_point_offset_x = 0.05
    dirs, _ = camera_rays(cam.sensor_dict())
    dirs = np.asarray(dirs)
    for x, y in ((0, 0), (47, 3), (20, 31)):
        o, d = pixel_ray(cam, x, y)
        assert np.allclose(o, cam.center) and _angle(d, dirs[y, x]) < 1e-3


def test_cast_median_depth_is_the_first_surface(scenes):
    """Through a sphere of 0.95-opaque surfels the mean composited depth takes in its back;
    the median depth (where the opacity reaches the level) is the front surface."""
    from comgs_dr.surfels import raycast
    trace = raycast.trace_scene(scenes["sphere"])
    g = np.linspace(-0.6, 0.6, 15)
    o = np.array([[x, -4.0, z] for x in g for z in g] + [[3.0, -4.0, 0.0]])
    d = np.tile([0.0, 1.0, 0.0], (len(o), 1))
    r = raycast.cast(trace, o, d, level=0.5)
    hits = np.array([_ray_sphere(p, q) for p, q in zip(o[:-1], d[:-1])])
    true_t = ((hits - o[:-1]) * d[:-1]).sum(1)
    assert np.abs(r["depth"][:-1] - true_t).max() < 4e-3 and r["weight"][:-1].min() > 0.9
    assert np.abs(r["mean_depth"][:-1] - true_t).max() > 0.05         # the back mixed in
    assert max(_angle(n, h) for n, h in zip(r["normal"][:-1], hits)) < 6.0   # facing the ray
    assert np.isnan(r["depth"][-1]) and r["weight"][-1] == 0.0


def test_object_base_and_pose():
    from comgs_dr.stages.place import PlaceConfig, object_shape, pose, up_rotation
    shape = object_shape(_box(), PlaceConfig())
    assert np.allclose(shape.base, [0.3, -0.2, 0.1], atol=0.01)
    assert shape.size == pytest.approx(np.linalg.norm(BOX), rel=0.03)
    up = np.array([0.0, 0.6, 0.8])
    r = up_rotation(up, 30.0)
    assert np.allclose(r @ [0, 0, 1], up) and np.allclose(r.T @ r, np.eye(3))
    sim = pose(shape, [1.0, 2.0, 3.0], up, PlaceConfig(scale=2.0, yaw_deg=30.0))
    assert np.allclose(sim.points(shape.base[None])[0], [1, 2, 3])
    assert sim.scale == 2.0


# ----------------------------------------------------------------------------- placing

def test_flat_plane_base_on_the_hit_point_up_along_the_normal(scenes):
    plane, n = scenes["flat"]
    obj = scenes["box"]
    cam = _camera([0.5, -4.0, 3.0], [0.0, 0.0, 0.0])
    for px in ((24, 24), (10, 30), (38, 18)):
        r = _place(plane, obj, cam, px)
        o, d = (np.asarray(v) for v in (r["target"]["ray_origin"], r["target"]["ray_direction"]))
        size = r["object_size"]
        err = np.linalg.norm(r["base"] - _ray_plane(o, d, n)) / size
        assert err < 0.01, (px, err)
        assert _angle(r["up"], n) < 1.0 and r["tilt_deg"] < 1.0
        assert r["lift"]["lift"] < 0.005 * size
        placed = r["similarity"].points(_means(obj))
        heights = placed @ n
        assert np.quantile(heights, 0.005) > -0.005 * size           # lowest surfels clear
        assert heights.min() < 0.01 * size                           # ...and touch


def test_tilted_plane_normal_and_upright_lift(scenes):
    plane, n = scenes["tilted"]
    obj = scenes["box"]
    cam = _camera([0.0, -4.0, 3.0], [0.0, 0.0, 0.0])
    r = _place(plane, obj, cam, (24, 24))
    size = r["object_size"]
    o, d = (np.asarray(v) for v in (r["target"]["ray_origin"], r["target"]["ray_direction"]))
    hit = _ray_plane(o, d, n)
    assert np.linalg.norm(r["base"] - hit) / size < 0.01
    assert _angle(r["up"], n) < 1.0 and r["tilt_deg"] == pytest.approx(20.0, abs=1.0)
    assert r["lift"]["lift"] < 0.005 * size

    u = _place(plane, obj, cam, (24, 24), upright=True, yaw_deg=10.0)
    assert np.allclose(u["up"], [0, 0, 1]) and u["tilt_deg"] == pytest.approx(20.0, abs=1.0)
    placed = u["similarity"].points(_means(obj))
    heights = placed @ n                                              # above the tilted plane
    assert u["lift"]["lift"] > 0.05 * size                            # raised on the slope
    assert np.quantile(heights, 0.005) > -0.005 * size and heights.min() > -0.01 * size
    assert heights.min() < 0.01 * size                                # touching, not floating
    # the lift is along world up, from the hit point
    assert np.allclose(u["base"], hit + u["lift"]["lift"] * np.array([0, 0, 1]), atol=0.01 * size)

    from comgs_dr.stages.place import PlaceError
    with pytest.raises(PlaceError, match="steeper than max_tilt_deg 15"):
        _place(plane, obj, cam, (24, 24), upright=True, max_tilt_deg=15.0)


def test_lift_over_a_step():
    """Stood on the ground beside a 0.1-high step that reaches under its footprint, the object
    is raised onto the step: none of its surfels is inside it."""
    from comgs_dr.surfels.from_mesh import from_mesh
    from comgs_dr.stages.place import PlaceConfig, Target, place_object
    ground = trimesh.Trimesh(np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], float),
                             [[0, 1, 2], [0, 2, 3]], process=False)
    step = trimesh.creation.box(extents=(1.0, 2.0, 0.1))
    step.apply_translation([0.6, 0.0, 0.05])                    # top at z = 0.1 from x = 0.1
    scene = from_mesh(trimesh.util.concatenate([ground, step]), 16000, seed=4)
    obj = _box()
    r = place_object(scene, obj, Target(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]),
                                        None, {}), PlaceConfig(upright=True))
    size = r["object_size"]
    assert r["lift"]["lift"] == pytest.approx(0.1, abs=0.01 * size)
    placed = r["similarity"].points(_means(obj))
    assert placed[:, 2].min() > 0.1 - 0.01 * size
    assert r["base"][2] == pytest.approx(0.1, abs=0.01 * size)


def test_sphere_base_on_the_surface_up_along_the_radius(scenes):
    sphere, obj = scenes["sphere"], scenes["box"]
    cam = _camera([0.0, -4.0, 2.5], [0.0, 0.0, 0.0])
    for px in ((24, 24), (24, 16), (30, 20)):
        r = _place(sphere, obj, cam, px)
        size = r["object_size"]
        o, d = (np.asarray(v) for v in (r["target"]["ray_origin"], r["target"]["ray_direction"]))
        hit = _ray_sphere(o, d)
        assert np.linalg.norm(r["base"] - hit) / size < 0.01, px
        assert abs(np.linalg.norm(r["base"]) - SPHERE_R) / size < 0.01
        assert _angle(r["up"], hit) < 2.0, px                           # the radial normal
        placed = r["similarity"].points(_means(obj))
        assert np.quantile(np.linalg.norm(placed, axis=1), 0.005) > SPHERE_R - 0.005 * size


def test_at_a_point_and_the_errors(scenes):
    from comgs_dr.stages.place import PlaceConfig, PlaceError, Target, place_object
    sphere, obj = scenes["sphere"], scenes["box"]
    top = Target(np.array([0.0, 0.0, SPHERE_R]), np.array([0.0, 0.0, 1.0]), None, {})
    r = place_object(sphere, obj, top, PlaceConfig())
    assert np.linalg.norm(r["base"] - [0, 0, SPHERE_R]) < 0.005 * r["object_size"]
    assert _angle(r["up"], [0, 0, 1]) < 1.0
    side = _camera([0.0, -4.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(PlaceError, match="tilted 9[0-9].*steeper"):
        _place(sphere, obj, side, (24, 24), upright=True)
    with pytest.raises(PlaceError, match="hits nothing"):
        _place(sphere, obj, side, (1, 1))
    with pytest.raises(PlaceError, match="outside the 48×48 image"):
        _place(sphere, obj, side, (48, 3))
    with pytest.raises(PlaceError, match="larger than the scene"):
        _place(sphere, obj, side, (24, 24), scale=10.0)
    far = Target(np.array([5.0, 5.0, 5.0]), np.array([0.0, 0.0, 1.0]), None, {})
    with pytest.raises(PlaceError, match="no surfel within"):
        place_object(sphere, obj, far, PlaceConfig())


def test_placement_file_is_what_compose_reads(tmp_path):
    """Entries are added or replaced (others kept as written), in the dataset's frame: the
    world placement comes back through compose's ``W`` mapping."""
    from comgs_dr.data.types import rotation_to_z
    from comgs_dr.stages.place import to_source_frame, write_entry
    p = tmp_path / "t.json"
    p.write_text(json.dumps({"other": {"location": [1, 2, 3], "rotation": [0, 0, 90],
                                       "scale": 2}}))
    W = np.eye(4)
    W[:3, :3], W[:3, 3] = rotation_to_z([0.0, 1.0, 0.2]), [0.5, -1.0, 2.0]
    world = Similarity(0.7, rotation_to_z([0.3, 0.1, 1.0]).T, np.array([1.0, 2.0, 0.5]))
    src = to_source_frame(world, W)
    assert write_entry(p, "torus", src) is False
    got = read_placements(p)
    assert list(got) == ["other", "torus"]
    assert json.loads(p.read_text())["other"] == {"location": [1, 2, 3], "rotation": [0, 0, 90],
                                                  "scale": 2}
    s0 = got["torus"]                                      # compose's _place_objects mapping
    back = Similarity(s0.scale, W[:3, :3] @ s0.rotation, W[:3, :3] @ s0.translation + W[:3, 3])
    assert np.allclose(back.matrix, world.matrix)
    assert write_entry(p, "torus", world) is True and len(read_placements(p)) == 2
    p.write_text("{broken")
    with pytest.raises(ValueError, match="not valid UTF-8 JSON"):
        write_entry(p, "torus", world)


# ----------------------------------------------------------------------------- the command

@pytest.fixture(scope="module")
def runs(tmp_path_factory, scenes):
    """A step-1 run of the tilted plane (NeRF-layout dataset of 48 px images) and an object
    run of the box."""
    from PIL import Image

    from comgs_dr.surfels.io import save_ply
    from comgs_dr.train.run import write_run_info
    root = tmp_path_factory.mktemp("place")
    data, run, obj = root / "data", root / "scene_run", root / "object_run"
    (data / "train").mkdir(parents=True)
    frames = []
    for i, o in enumerate(([0.0, -4.0, 3.0], [3.0, -2.0, 2.5], [0.0, -4.0, 0.0])):
        Image.fromarray(np.full((RES, RES, 3), 90, np.uint8)).save(data / "train" / f"v{i}.png")
        c2w = _look_at(o, [0.0, 0.0, 0.0]) @ np.diag([-1.0, 1, -1, 1])   # Mitsuba -> OpenGL
        frames.append({"file_path": f"train/v{i}", "transform_matrix": c2w.tolist()})
    (data / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": math.radians(40.0), "frames": frames}))
    write_run_info(run, data, "scene", 1, False)
    save_ply(scenes["tilted"][0], run / "point_cloud.ply")
    obj.mkdir()
    save_ply(scenes["box"], obj / "point_cloud.ply")
    return {"run": run, "obj": obj, "root": root, "normal": scenes["tilted"][1]}


def test_cli_writes_and_appends_the_placement(runs, capsys):
    from comgs_dr import cli
    out = runs["root"] / "transform.json"
    argv = ["place", str(runs["run"]), "--object", f"box={runs['obj']}", "--out", str(out)]
    assert cli.main(argv + ["--view", "v0", "--pixel", "24", "24"]) == 0
    text = capsys.readouterr().out
    assert all(w in text for w in ("ray hits", "surface normal", "tilt 20", "lift", "wrote"))
    assert cli.main(argv[:3] + [f"box2={runs['obj']}", "--out", str(out), "--view", "1",
                                "--pixel", "20", "25", "--upright", "--yaw", "45",
                                "--scale", "0.5"]) == 0
    got = read_placements(out)
    assert list(got) == ["box", "box2"] and got["box2"].scale == 0.5
    assert _angle(got["box"].rotation @ [0, 0, 1], runs["normal"]) < 1.0
    assert np.allclose(got["box2"].rotation @ [0, 0, 1], [0, 0, 1])
    assert cli.main(argv + ["--at", "0", "0", "0"]) == 0
    assert "replaced 'box'" in capsys.readouterr().out
    assert np.linalg.norm(read_placements(out)["box"].points([[0.3, -0.2, 0.1]])[0]) < 0.01


@pytest.mark.parametrize("extra, message", [
    (["--view", "v9", "--pixel", "1", "1"], "no view 'v9'"),
    (["--view", "7", "--pixel", "1", "1"], "view index 7 is out of range"),
    (["--view", "v0", "--pixel", "60", "1"], "outside the 48×48 image"),
    (["--view", "v2", "--pixel", "24", "2"], "hits nothing"),
    (["--view", "v0", "--pixel", "24", "24", "--upright", "--max-tilt-deg", "10"],
     "steeper than max_tilt_deg 10"),
    (["--view", "v0", "--pixel", "24", "24", "--scale", "20"], "larger than the scene"),
    (["--view", "v0"], "--view VIEW --pixel X Y"),
    (["--at", "0", "0", "0", "--view", "v0", "--pixel", "1", "1"], "not both"),
    (["--view", "v0", "--pixel", "24", "24", "--floater-share", "0.7"], "floater_share"),
    (["--view", "v0", "--pixel", "24", "24", "--scale", "-1"], "scale must be"),
    (["--view", "v0", "--pixel", "nan", "24"], "--pixel"),
    (["--at", "0", "inf", "0"], "--at"),
])
def test_cli_errors_exit_2_and_say_why(runs, capsys, extra, message):
    from comgs_dr import cli
    out = runs["root"] / "bad.json"
    assert cli.main(["place", str(runs["run"]), "--object", f"box={runs['obj']}", "--out",
                     str(out)] + extra) == 2
    err = capsys.readouterr().err
    assert err.startswith("comgs place: error:") and message in err, err
    assert not out.exists()


def test_cli_missing_runs(runs, tmp_path, capsys):
    from comgs_dr import cli
    base = ["--view", "v0", "--pixel", "24", "24", "--out", str(tmp_path / "t.json")]
    assert cli.main(["place", str(tmp_path), "--object", f"a={runs['obj']}"] + base) == 2
    assert "run.json not found" in capsys.readouterr().err
    assert cli.main(["place", str(runs["run"]), "--object", f"a={tmp_path}"] + base) == 2
    assert "no point_cloud.ply" in capsys.readouterr().err
    assert cli.main(["place", str(runs["run"]), "--object", "a b=x"] + base) == 2
    assert "object names" in capsys.readouterr().err


# ----------------------------------------------------------------------------- measurement

def measure(grid: int = 7) -> dict:
    """The numbers of docs/place.md: over a ``grid`` × ``grid`` of pixels on the flat and the
    tilted plane and on the sphere, the base's distance to the true ray–surface point (× the
    object's size), the up vector's angle to the true normal, the lowest object surfel's
    height over the true surface (× size) and the time of one placement (the ray, the
    normal, the lift; the scene's Mitsuba shapes built once). ``python tests/test_place.py``."""
    import time

    from comgs_dr.stages.place import PlaceConfig, PlaceError, pixel_target, place_object
    from comgs_dr.surfels import raycast
    comgs_dr.set_variant("llvm_ad_rgb")
    obj = _box()
    cases = {"flat plane": (*_plane(0.0), [0.5, -4.0, 3.0], "plane", {}),
             "tilted plane (20°)": (*_plane(20.0), [0.0, -4.0, 3.0], "plane", {}),
             "tilted plane, --upright": (*_plane(20.0), [0.0, -4.0, 3.0], "plane",
                                         {"upright": True}),
             "sphere": (_sphere(), None, [0.0, -4.0, 2.5], "sphere", {})}
    out = {}
    for label, (scene, n, eye, kind, kw) in cases.items():
        cam, cfg = _camera(eye, [0.0, 0.0, 0.0]), PlaceConfig(**kw)
        trace = raycast.trace_scene(scene)
        pixel_target(trace, cam, RES / 2, RES / 2, cfg)                  # compile the kernels
        errs, angles, clear, secs = [], [], [], []
        obj_pts = _means(obj)
        for y in np.linspace(4, RES - 5, grid):
            for x in np.linspace(4, RES - 5, grid):
                t = time.perf_counter()
                try:
                    r = place_object(scene, obj, pixel_target(trace, cam, x, y, cfg), cfg, trace)
                except PlaceError:
                    continue                                         # off the sphere
                secs.append(time.perf_counter() - t)
                o, d = (np.asarray(v) for v in (r["target"]["ray_origin"],
                                                r["target"]["ray_direction"]))
                size = r["object_size"]
                hit = _ray_plane(o, d, n) if kind == "plane" else _ray_sphere(o, d)
                true_n = n if kind == "plane" else hit / SPHERE_R
                placed = r["similarity"].points(obj_pts)
                h = placed @ n if kind == "plane" else np.linalg.norm(placed, axis=1) - SPHERE_R
                if kw.get("upright"):          # the base is lifted: measure it on the surface
                    errs.append(abs(h.min()) / size)
                else:
                    errs.append(np.linalg.norm(r["base"] - hit) / size)
                angles.append(_angle(r["up"], [0, 0, 1] if kw.get("upright") else true_n))
                clear.append(h.min() / size)
        out[label] = {"placements": len(errs), "base_error_max": float(np.max(errs)),
                      "base_error_median": float(np.median(errs)),
                      "up_error_deg_max": float(np.max(angles)),
                      "lowest_surfel_min": float(np.min(clear)),
                      "lowest_surfel_max": float(np.max(clear)),
                      "seconds_median": float(np.median(secs))}
    return out


if __name__ == "__main__":
    for k, v in measure().items():
        print(f"{k:26s} n={v['placements']:2d}  base error max {v['base_error_max']:.3%} "
              f"(median {v['base_error_median']:.3%}) of the object size, up error max "
              f"{v['up_error_deg_max']:.2f}°, lowest surfel {v['lowest_surfel_min']:+.3%} .. "
              f"{v['lowest_surfel_max']:+.3%}, {v['seconds_median'] * 1000:.0f} ms/placement")
