"""Dataset loaders of reconstruction step 1 (comgs_dr.data).

Tiny datasets (<= 26x18 px, <= 10 views) are written here with numpy + PIL + json; the
ground truth is an OpenCV pinhole projection u = K (R X + t) of known points. Camera
conversions are checked twice: with ``Camera.project`` and with the Mitsuba sensor built
from ``camera.sensor_dict()`` (``sample_direction`` uv and a ``sample_ray`` through the
expected pixel), to 0.5 px (the actual errors are ~1e-4 px, float32).
"""
import json

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from PIL import Image

from comgs_dr.core.hostarray import to_jit
from comgs_dr.data import load as D

TOL_PX = 0.5
X_TEST = np.array([[0.3, -0.2, 0.25], [-0.4, 0.1, -0.3], [0.0, 0.0, 0.0]])  # [3, 3] world


# ----------------------------------------------------------------------------- helpers

def look_at_cv(center, target=(0, 0, 0), up=(0, 0, 1)):
    """OpenCV world-to-camera (R [3, 3], t [3]) of a camera at ``center`` facing ``target``."""
    c, up = np.asarray(center, float), np.asarray(up, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])                   # rows: camera axes in world
    return r, -r @ c


def c2w_cv(r, t):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r.T, -r.T @ t
    return m


def project_cv(K, r, t, X):
    pc = np.asarray(X) @ r.T + t
    uv = pc @ np.asarray(K).T
    return uv[:, :2] / uv[:, 2:3]


def ring_cameras(n, radius=4.0, up=(0, 0, 1), height=1.0, jitter=0.0):
    """n cameras around the origin (on a ring in the plane orthogonal to ``up``)."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0.3, 0.1])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    cams = []
    for i in range(n):
        phi = 2 * np.pi * i / n
        c = radius * (np.cos(phi) * a + np.sin(phi) * b) + height * up
        target = jitter * np.array([np.sin(3 * i), np.cos(5 * i), np.sin(7 * i)])
        cams.append(look_at_cv(c, target, up))
    return cams


def assert_projects(cam: D.Camera, X, uv_expected):
    """Camera.project and the Mitsuba sensor both put world points X at uv_expected."""
    uv, depth = cam.project(X)
    assert np.all(depth > 0)
    np.testing.assert_allclose(uv, uv_expected, atol=TOL_PX)
    sensor = mi.load_dict(cam.sensor_dict())
    it = dr.zeros(mi.Interaction3f, len(X))
    it.p = to_jit(mi.Point3f, np.asarray(X).T)
    ds, _ = sensor.sample_direction(it, mi.Point2f(0.5, 0.5))
    np.testing.assert_allclose(np.stack([ds.uv.x.numpy(), ds.uv.y.numpy()], 1),
                               uv_expected, atol=TOL_PX)
    pos = np.asarray(uv_expected, np.float32) / [cam.width, cam.height]
    ray, _ = sensor.sample_ray(0.0, 0.5, to_jit(mi.Point2f, pos.T), mi.Point2f(0.5, 0.5))
    o = np.stack([c.numpy() for c in (ray.o.x, ray.o.y, ray.o.z)], 1)
    d = np.stack([c.numpy() for c in (ray.d.x, ray.d.y, ray.d.z)], 1)
    v = np.asarray(X) - o
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    angle = np.arccos(np.clip(np.sum(v * d, 1), -1, 1))
    assert np.all(cam.fx * angle < TOL_PX), cam.fx * angle


def write_png(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(np.clip(arr, 0, 1) * 255).astype(np.uint8)).save(path)


def rand_image(rng, h, w, c=3):
    return np.round(rng.uniform(0, 1, (h, w, c)) * 255) / 255


# ----------------------------------------------------------------------------- NeRF

def write_nerf(root, cams, w, h, rng, intr=None, splits=("train", "test"), ext=False):
    """NeRF-synthetic folder; ``cams`` per split; intrinsics keys ``intr`` (default
    camera_angle_x = 0.9). Returns {split: [rgba [H, W, 4]]}."""
    images = {}
    for split in splits:
        frames, images[split] = [], []
        for i, (r, t) in enumerate(cams[split]):
            rgba = rand_image(rng, h, w, 4)
            rgba[0, 0, 3], rgba[1, 1, 3] = 0.0, 1.0
            write_png(root / split / f"r_{i}.png", rgba)
            images[split].append(rgba)
            gl = c2w_cv(r, t) @ np.diag([1.0, -1.0, -1.0, 1.0])
            frames.append({"file_path": f"./{split}/r_{i}" + (".png" if ext else ""),
                           "transform_matrix": gl.tolist()})
        body = dict(intr or {"camera_angle_x": 0.9}, frames=frames)
        (root / f"transforms_{split}.json").write_text(json.dumps(body))
    return images


@pytest.mark.parametrize("scale", [1, 2])
@pytest.mark.parametrize("intr", [None, {"fl_x": 21.0, "fl_y": 21.1, "cx": 10.3, "cy": 8.6,
                                         "w": 26, "h": 18}])
def test_nerf_cameras_project(tmp_path, rng, scale, intr):
    w, h = 26, 18
    cams = {"train": ring_cameras(3), "test": ring_cameras(2, height=2.0)}
    write_nerf(tmp_path, cams, w, h, rng, intr, ext=intr is not None)
    sd = D.load_nerf_synthetic(tmp_path, resolution_scale=scale)
    assert [v.name for v in sd.train] == ["train/r_0", "train/r_1", "train/r_2"]
    if intr is None:
        f = 0.5 * w / np.tan(0.45)
        K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    else:
        K = np.array([[21.0, 0, 10.3], [0, 21.1, 8.6], [0, 0, 1]])
    for view, (r, t) in zip(sd.train + sd.test, cams["train"] + cams["test"]):
        assert (view.camera.width, view.camera.height) == (w // scale, h // scale)
        assert view.image.shape == (h // scale, w // scale, 3) and view.image.dtype == np.float32
        assert_projects(view.camera, X_TEST, project_cv(K, r, t, X_TEST) / scale)


@pytest.mark.parametrize("white", [False, True])
def test_nerf_compositing_and_scale(tmp_path, rng, white):
    w, h = 8, 6
    cams = {"train": ring_cameras(2), "test": ring_cameras(1)}
    imgs = write_nerf(tmp_path, cams, w, h, rng)
    bg = float(white)
    rgba = imgs["train"][1]
    want = rgba[..., :3] * rgba[..., 3:] + bg * (1 - rgba[..., 3:])
    sd = D.load_nerf_synthetic(tmp_path, white_background=white)
    assert sd.white_background is white and np.all(sd.background == bg)
    np.testing.assert_allclose(sd.train[1].image, want, atol=1e-6)
    np.testing.assert_allclose(sd.train[1].mask, rgba[..., 3], atol=1e-6)
    half = D.load_nerf_synthetic(tmp_path, white_background=white, resolution_scale=2)
    np.testing.assert_allclose(half.train[1].image,
                               want.reshape(3, 2, 4, 2, 3).mean((1, 3)), atol=1e-6)
    np.testing.assert_allclose(half.train[1].mask,
                               rgba[..., 3].reshape(3, 2, 4, 2).mean((1, 3)), atol=1e-6)


def test_nerf_holdout_and_max_views(tmp_path, rng):
    cams = {"train": ring_cameras(10)}
    write_nerf(tmp_path, cams, 4, 4, rng, splits=("train",))
    sd = D.load_nerf_synthetic(tmp_path)
    assert [v.name for v in sd.test] == ["train/r_0", "train/r_8"]
    assert [v.name for v in sd.train] == [f"train/r_{i}" for i in (1, 2, 3, 4, 5, 6, 7, 9)]
    few = D.load_nerf_synthetic(tmp_path, max_views=3)
    assert [v.name for v in few.train] == ["train/r_1", "train/r_5", "train/r_9"]
    center, radius = sd.bounds
    assert np.linalg.norm(center - [0, 0, 1]) < 1e-6 and radius == pytest.approx(4.4)


def test_generator_dataset_roundtrip(tmp_path):
    """A dataset from comgs_dr.data.synthetic loads with the cameras it recorded."""
    trimesh = pytest.importorskip("trimesh")
    from comgs_dr.data import synthetic as syn
    trimesh.creation.icosphere(subdivisions=1, radius=0.7).export(tmp_path / "ball.ply")
    mi.Bitmap(np.full((8, 16, 3), 0.8, np.float32)).write(str(tmp_path / "sky.exr"))
    cfg = syn.ObjectDatasetConfig(mesh=tmp_path / "ball.ply", envmap=tmp_path / "sky.exr",
                                  out_dir=tmp_path / "ds", n_train=3, n_test=3, resolution=16,
                                  spp=2, spp_aov=1, max_depth=2, relight_envmaps=(),
                                  texture=None)
    syn.make_object_dataset(cfg, progress=False)
    sd = D.load_dataset(tmp_path / "ds", white_background=True)
    assert len(sd.train) == 3 and len(sd.test) == 3 and sd.meta["format"] == "nerf_synthetic"
    for split, views in (("train", sd.train), ("test", sd.test)):
        frames = json.loads((tmp_path / "ds" / f"transforms_{split}.json").read_text())["frames"]
        for v, fr in zip(views, frames):
            np.testing.assert_allclose(v.camera.to_world, fr["to_world_mitsuba"], atol=1e-6)
            assert v.camera.fov_x_deg == pytest.approx(cfg.fov_deg)
            assert v.mask.shape == (16, 16) and 0.0 < v.mask.mean() < 1.0
            alpha = np.asarray(Image.open(v.path), np.float32)[..., 3] / 255
            np.testing.assert_allclose(v.mask, alpha, atol=1e-6)


def test_generator_sfm_points_are_visible_surface_points(tmp_path):
    """``sfm_points``: points3d.ply with surface points that >= 2 training cameras see
    (on a convex ball: in front of >= 2 cameras' tangent planes), read by the NeRF loader."""
    trimesh = pytest.importorskip("trimesh")
    from comgs_dr.data import synthetic as syn
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.7)
    ball.export(tmp_path / "ball.ply")
    mi.Bitmap(np.full((8, 16, 3), 0.8, np.float32)).write(str(tmp_path / "sky.exr"))
    cfg = syn.ObjectDatasetConfig(mesh=tmp_path / "ball.ply", envmap=tmp_path / "sky.exr",
                                  out_dir=tmp_path / "ds", n_train=4, n_test=1, resolution=16,
                                  spp=2, spp_aov=1, max_depth=2, relight_envmaps=(),
                                  texture=None, sfm_points=300)
    syn.make_object_dataset(cfg, progress=False)
    sd = D.load_dataset(tmp_path / "ds")
    assert sd.points.shape == (300, 3) and sd.colors.shape == (300, 3)
    assert 0.0 <= sd.colors.min() and sd.colors.max() <= 1.0 and sd.colors.mean() > 0.2
    r = np.linalg.norm(sd.points, axis=1)
    meta = json.loads((tmp_path / "ds" / "meta.json").read_text())
    rw = 0.7 * meta["object"]["object_to_world"][0][0]                 # ball radius in world
    assert np.all(np.abs(r - rw) < 0.03 * rw)
    cams = np.array([v.camera.to_world[:3, 3] for v in sd.train])    # [4, 3]
    facing = ((cams[None] - sd.points[:, None]) * sd.points[:, None]).sum(-1) > -0.02 * rw
    assert facing.sum(1).min() >= 2
    # the back of the ball (seen by no camera) gets no point although it has area
    back = -cams.mean(0) / np.linalg.norm(cams.mean(0))
    assert (sd.points @ back / r > 0.9).sum() == 0


def test_bad_points_ply(nerf):
    from comgs_dr.data.sfm_points import write_points_ply
    write_points_ply(nerf / "points3d.ply", np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 0, 0]]))
    _raises(lambda: D.load_nerf_synthetic(nerf), nerf / "points3d.ply", "non-finite")
    (nerf / "points3d.ply").write_bytes(b"ply\nformat ascii 1.0\nelement face 0\nend_header\n")
    _raises(lambda: D.load_nerf_synthetic(nerf), nerf / "points3d.ply", "x/y/z")
    pts = np.random.default_rng(0).normal(size=(10, 3))
    write_points_ply(nerf / "points3d.ply", pts)                     # no colour: fine
    sd = D.load_nerf_synthetic(nerf)
    np.testing.assert_allclose(sd.points, pts, atol=1e-6)
    assert sd.colors is None


# ----------------------------------------------------------------------------- COLMAP

def quat_wxyz(r):
    import pycolmap
    x, y, z, w = pycolmap.Rotation3d(np.asarray(r, float)).quat
    return w, x, y, z


def write_colmap_text(model, cams, names, cam_line, points, order=None):
    """cameras.txt (one camera), images.txt, points3D.txt written by hand."""
    model.mkdir(parents=True, exist_ok=True)
    (model / "cameras.txt").write_text(f"# camera\n1 {cam_line}\n")
    lines = ["# images"]
    for i in order if order is not None else range(len(cams)):
        (r, t), q = cams[i], quat_wxyz(cams[i][0])
        lines += [f"{i + 1} {' '.join(map(repr, map(float, q)))} "
                  f"{' '.join(map(repr, map(float, t)))} 1 {names[i]}", ""]
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("".join(
        f"{j + 1} {' '.join(repr(float(c)) for c in p)} 255 128 0 0.5\n"
        for j, p in enumerate(points)))


def make_colmap(root, rng, n=9, w=26, h=18, up=(0, -1, 0), cam_line=None, masks=False):
    """COLMAP scene with COLMAP-like world up (-Y), non-centred principal point."""
    cams = ring_cameras(n, up=up, height=0.0)
    names = [f"img_{i:02d}.jpg" for i in range(n)]
    order = list(rng.permutation(n))
    write_colmap_text(root / "sparse" / "0", cams, names,
                      cam_line or f"PINHOLE {w} {h} 22.0 22.1 11.4 7.9", X_TEST, order)
    (root / "images").mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        Image.fromarray((rand_image(rng, h, w) * 255).astype(np.uint8)).save(root / "images" / name)
        if masks:
            m = np.zeros((h, w))
            m[2:h - 2, i:w - 3] = 1.0
            write_png(root / "masks" / f"img_{i:02d}.png", m)
    K = np.array([[22.0, 0, 11.4], [0, 22.1, 7.9], [0, 0, 1]])
    return cams, names, K


@pytest.mark.parametrize("scale", [1, 2])
def test_colmap_text_cameras_points_split(tmp_path, rng, scale):
    cams, names, K = make_colmap(tmp_path, rng)
    sd = D.load_colmap(tmp_path, resolution_scale=scale, up="none")
    assert [v.name for v in sd.test] == ["img_00.jpg", "img_08.jpg"]
    assert [v.name for v in sd.train] == names[1:8]
    by_name = dict(zip(names, cams))
    for v in sd.train + sd.test:
        r, t = by_name[v.name]
        assert (v.camera.width, v.camera.height) == (26 // scale, 18 // scale)
        assert_projects(v.camera, X_TEST, project_cv(K, r, t, X_TEST) / scale)
    np.testing.assert_allclose(sd.points, X_TEST, atol=1e-6)
    np.testing.assert_allclose(sd.colors, [[1.0, 128 / 255, 0.0]] * 3, atol=1e-6)
    assert sd.points.dtype == np.float32 and sd.colors.dtype == np.float32
    assert D.load_dataset(tmp_path, up="none").meta["format"] == "colmap"


def test_colmap_binary_model(tmp_path, rng):
    import pycolmap
    cams, names, K = make_colmap(tmp_path, rng, n=3)
    text = tmp_path / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(text))
    for f in text.iterdir():
        f.unlink()
    text.rmdir()
    rec.write_binary(str(tmp_path / "sparse"))                  # model directly in sparse/
    assert (tmp_path / "sparse" / "cameras.bin").is_file()
    sd = D.load_colmap(tmp_path, up="none", test_every=None)
    assert sd.test == [] and [v.name for v in sd.train] == names
    for v, (r, t) in zip(sd.train, cams):
        assert_projects(v.camera, X_TEST, project_cv(K, r, t, X_TEST))


def test_colmap_up_auto(tmp_path, rng):
    up = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    cams, names, K = make_colmap(tmp_path, rng, n=4, up=up)
    sd = D.load_colmap(tmp_path, up="auto", test_every=None)
    rot = sd.world_from_source[:3, :3]
    np.testing.assert_allclose(rot @ up, [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(sd.points, X_TEST @ rot.T, atol=1e-6)
    for v, (r, t) in zip(sd.train, cams):
        np.testing.assert_allclose(v.camera.to_world[:3, 1], [0, 0, 1], atol=1e-9)  # cam up
        assert_projects(v.camera, sd.points, project_cv(K, r, t, X_TEST))


def test_colmap_masks_and_resized_images(tmp_path, rng):
    make_colmap(tmp_path, rng, n=3, masks=True)
    sd = D.load_colmap(tmp_path, masks="masks", test_every=None, resolution_scale=2)
    m = sd.train[1].mask
    want = np.zeros((18, 26), np.float32)
    want[2:16, 1:23] = 1
    np.testing.assert_allclose(m, want.reshape(9, 2, 13, 2).mean((1, 3)), atol=1e-6)
    # images_2: half-size copies with the full-size model -> intrinsics follow the files
    for v in sd.train:
        (tmp_path / "images_2").mkdir(exist_ok=True)
        Image.fromarray((v.image * 255).astype(np.uint8)).save(tmp_path / "images_2" / v.name)
    small = D.load_colmap(tmp_path, images="images_2", test_every=None)
    for a, b in zip(small.train, sd.train):
        assert (a.camera.width, a.camera.height) == (b.camera.width, b.camera.height) == (13, 9)
        np.testing.assert_allclose(a.camera.intrinsics(), b.camera.intrinsics(), atol=1e-9)
        np.testing.assert_allclose(a.camera.to_world, b.camera.to_world, atol=1e-12)


def test_colmap_rgba_images_composited(tmp_path, rng):
    """load_dataset passes white_background on; RGBA photos are composited, alpha = mask."""
    make_colmap(tmp_path, rng, n=2)
    rgba = rand_image(rng, 18, 26, 4)
    Image.fromarray((rgba * 255).astype(np.uint8)).save(tmp_path / "images" / "img_01.jpg",
                                                         format="PNG")
    sd = D.load_dataset(tmp_path, white_background=True, test_every=None)
    assert sd.white_background and sd.train[0].mask is None
    np.testing.assert_allclose(sd.train[1].mask, rgba[..., 3], atol=1e-6)
    np.testing.assert_allclose(sd.train[1].image, rgba[..., :3] * rgba[..., 3:]
                               + (1 - rgba[..., 3:]), atol=1e-6)


def test_colmap_radial_models(tmp_path, rng):
    make_colmap(tmp_path, rng, n=2, cam_line="SIMPLE_RADIAL 26 18 22.0 13.0 9.0 0.0")
    assert len(D.load_colmap(tmp_path, test_every=None).train) == 2   # k = 0: a pinhole
    write_colmap_text(tmp_path / "sparse" / "0", ring_cameras(2), ["img_00.jpg", "img_01.jpg"],
                      "SIMPLE_RADIAL 26 18 22.0 13.0 9.0 0.05", X_TEST)
    with pytest.raises(D.DatasetError, match="image_undistorter") as e:
        D.load_colmap(tmp_path)
    assert str(tmp_path / "sparse" / "0") in str(e.value)
    write_colmap_text(tmp_path / "sparse" / "0", ring_cameras(2), ["img_00.jpg", "img_01.jpg"],
                      "OPENCV_FISHEYE 26 18 22.0 22.0 13.0 9.0 0 0 0 0", X_TEST)
    with pytest.raises(D.DatasetError, match="unsupported camera model OPENCV_FISHEYE"):
        D.load_colmap(tmp_path)


# ----------------------------------------------------------------------------- LLFF

def write_llff(root, cams, w, h, focal, rng, folder="images", n_images=None):
    """poses_bounds.npy for a (w, h) camera of ``focal``; images of size (w, h) // 2."""
    rows = []
    for r, t in cams:
        m = c2w_cv(r, t)
        llff = np.stack([m[:3, 1], m[:3, 0], -m[:3, 2], m[:3, 3], [h, w, focal]], 1)  # [3, 5]
        rows.append(np.concatenate([llff.ravel(), [0.5, 9.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    for i in range(len(cams) if n_images is None else n_images):
        write_png(root / folder / f"IMG_{i:03d}.png", rand_image(rng, h // 2, w // 2))


@pytest.mark.parametrize("scale", [1, 2])
def test_llff_cameras_project(tmp_path, rng, scale):
    cams = ring_cameras(9, up=(0, -1, 0), height=0.5, jitter=0.2)
    write_llff(tmp_path, cams, 52, 36, 44.0, rng, folder="images_2")  # files: 26x18
    sd = D.load_llff(tmp_path, resolution_scale=scale, up="none")
    assert [v.name for v in sd.test] == ["IMG_000", "IMG_008"] and len(sd.train) == 7
    assert sd.meta["near_far"]["IMG_003"] == (0.5, 9.0)
    K = np.array([[22.0, 0, 13.0], [0, 22.0, 9.0], [0, 0, 1]])     # focal rescaled to files
    for v in sd.train + sd.test:
        r, t = cams[int(v.name[4:])]
        assert_projects(v.camera, X_TEST, project_cv(K, r, t, X_TEST) / scale)
    auto = D.load_dataset(tmp_path)                                 # LLFF, up="auto"
    assert auto.meta["format"] == "llff"
    ups = np.array([v.camera.to_world[:3, 1] for v in auto.views])
    assert np.all(ups[:, 2] > 0.97)
    if scale == 1:              # render-comp --cameras poses_bounds.npy: the same test views
        from comgs_dr.data.comp_folder import camera_source
        W = np.asarray(auto.world_from_source, np.float64)
        cs = camera_source(tmp_path / "poses_bounds.npy", W, res=(20, 10))
        assert [c["name"] for c in cs] == ["IMG_000", "IMG_008"]
        with pytest.raises(ValueError, match="not the composition's"):     # another frame
            camera_source(tmp_path, W @ np.diag([1.0, -1, -1, 1]), res=(20, 10))
        for c, v in zip(cs, auto.test):         # the loader's frame; world_from_source unused
            np.testing.assert_array_equal(c["to_world"], v.camera.to_world)
            assert (c["width"], c["height"]) == (20, 10) and c["fov_x_deg"] == v.camera.fov_x_deg


# ----------------------------------------------------------------------------- camera

def test_camera_principal_point_and_focal_check():
    r, t = look_at_cv([3.0, -2.0, 1.5])
    K = np.array([[30.0, 0, 9.0], [0, 30.0, 13.0], [0, 0, 1]])
    cam = D.Camera.from_intrinsics(c2w_cv(r, t) @ D.MITSUBA_FROM_OPENCV, 24, 20, 30.0, 30.0,
                                   9.0, 13.0)
    assert cam.principal_point_offset_x == pytest.approx(0.5 - 9 / 24)
    np.testing.assert_allclose(cam.intrinsics(), K)
    assert_projects(cam, X_TEST, project_cv(K, r, t, X_TEST))
    d = cam.sensor_dict(spp=4)
    assert d["film"]["rfilter"]["type"] == "box" and d["sampler"]["sample_count"] == 4
    with pytest.raises(D.DatasetError, match="fx=30 and fy=31"):
        D.Camera.from_intrinsics(np.eye(4), 24, 20, 30.0, 31.0, 12.0, 10.0, where="cam.json")


# ----------------------------------------------------------------------------- bad data

@pytest.fixture
def nerf(tmp_path, rng):
    write_nerf(tmp_path, {"train": ring_cameras(2), "test": ring_cameras(1)}, 6, 4, rng)
    return tmp_path


def _edit_json(path, fn):
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


def _raises(fn, *needles):
    with pytest.raises(D.DatasetError) as e:
        fn()
    for s in needles:
        assert str(s) in str(e.value), str(e.value)
    return str(e.value)


def test_bad_missing_folder_and_json(tmp_path):
    _raises(lambda: D.load_nerf_synthetic(tmp_path / "nope"), tmp_path / "nope")
    _raises(lambda: D.load_nerf_synthetic(tmp_path), tmp_path / "transforms_train.json")
    _raises(lambda: D.load_colmap(tmp_path), tmp_path, "sparse")
    _raises(lambda: D.load_llff(tmp_path), tmp_path / "poses_bounds.npy")
    _raises(lambda: D.load_dataset(tmp_path), tmp_path, "unknown dataset layout")


def test_bad_missing_images(nerf, tmp_path, rng):
    for i in range(2):
        (nerf / "train" / f"r_{i}.png").unlink()
    msg = _raises(lambda: D.load_nerf_synthetic(nerf), nerf / "transforms_train.json",
                  "2 of 2", "./train/r_0", "./train/r_1")
    assert "missing" in msg
    col = tmp_path / "col"
    make_colmap(col, rng, n=3)
    (col / "images" / "img_01.jpg").unlink()
    _raises(lambda: D.load_colmap(col), col / "sparse" / "0", "img_01.jpg")


def test_bad_count_mismatch(tmp_path, rng):
    write_llff(tmp_path, ring_cameras(3), 8, 8, 10.0, rng, n_images=2)
    _raises(lambda: D.load_llff(tmp_path), tmp_path / "images", "2 images", "3 poses")


@pytest.mark.parametrize("cols,value,needle", [(1, float("nan"), "non-finite"),
                                               (3, 0.0, "not invertible")])
def test_bad_poses(nerf, cols, value, needle):
    def corrupt(d):
        m = np.array(d["frames"][1]["transform_matrix"])
        m[:3, :cols] = value
        d["frames"][1]["transform_matrix"] = m.tolist()
    _edit_json(nerf / "transforms_train.json", corrupt)
    _raises(lambda: D.load_nerf_synthetic(nerf), nerf / "transforms_train.json", "frame 1",
            "./train/r_1", needle)


def test_bad_llff_pose(tmp_path, rng):
    write_llff(tmp_path, ring_cameras(2), 8, 8, 10.0, rng)
    pb = np.load(tmp_path / "poses_bounds.npy")
    pb[1, 3] = np.inf
    np.save(tmp_path / "poses_bounds.npy", pb)
    _raises(lambda: D.load_llff(tmp_path), tmp_path / "poses_bounds.npy", "IMG_001.png",
            "non-finite")


def test_absurd_camera_translation_is_a_clear_error(tmp_path, rng):
    """A finite pose 1e200 away loaded before, with an infinite scene extent (and a NumPy
    overflow warning): it is a damaged file, named with the pose."""
    import warnings
    write_llff(tmp_path, ring_cameras(2), 8, 8, 10.0, rng)
    pb = np.load(tmp_path / "poses_bounds.npy")
    pb[1, 3] = 1e200
    np.save(tmp_path / "poses_bounds.npy", pb)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                       # no overflow on the way
        _raises(lambda: D.load_llff(tmp_path), tmp_path / "poses_bounds.npy", "IMG_001.png",
                "beyond 1e+12 scene units")


def test_bad_corrupt_image(nerf):
    (nerf / "test" / "r_0.png").write_bytes(b"\x89PNG not really")
    _raises(lambda: D.load_nerf_synthetic(nerf), nerf / "test" / "r_0.png", "corrupt")


def test_bad_mask_size(tmp_path, rng):
    make_colmap(tmp_path, rng, n=2, masks=True)
    write_png(tmp_path / "masks" / "img_01.png", np.ones((5, 5)))
    _raises(lambda: D.load_colmap(tmp_path, masks="masks", test_every=None),
            tmp_path / "masks" / "img_01.png", "5x5", "26x18")
    (tmp_path / "masks" / "img_01.png").unlink()
    _raises(lambda: D.load_colmap(tmp_path, masks="masks"), tmp_path / "masks", "img_01.jpg")


def test_bad_empty_splits(nerf, tmp_path, rng):
    _edit_json(nerf / "transforms_test.json", lambda d: d.update(frames=[]))
    _raises(lambda: D.load_nerf_synthetic(nerf), nerf / "transforms_test.json", "empty split")
    one = tmp_path / "one"
    write_nerf(one, {"train": ring_cameras(1)}, 4, 4, rng, splits=("train",))
    _raises(lambda: D.load_nerf_synthetic(one), one / "transforms_train.json", "no training")


def test_bad_intrinsics(nerf):
    def focal(d):
        del d["camera_angle_x"]
        d.update(fl_x=10.0, fl_y=12.0)
    _edit_json(nerf / "transforms_train.json", focal)
    _raises(lambda: D.load_nerf_synthetic(nerf), "r_0.png", "fx=10 and fy=12")
    _edit_json(nerf / "transforms_train.json", lambda d: d.update(fl_y=10.0, k1=0.1))
    _raises(lambda: D.load_nerf_synthetic(nerf), nerf / "transforms_train.json", "undistort")


@pytest.mark.parametrize("fmt", ["nerf", "colmap", "llff"])
def test_cameras_only_match_the_full_load(tmp_path, rng, fmt):
    """``pixels=False`` (what compose, relight, export-mesh and render-comp load): the same
    cameras, names, splits and frame as the full load, the images not decoded (zero-stride
    blanks of the right shape)."""
    if fmt == "nerf":
        write_nerf(tmp_path, {"train": ring_cameras(5), "test": ring_cameras(2)}, 26, 18, rng)
    elif fmt == "colmap":
        make_colmap(tmp_path, rng)
    else:
        write_llff(tmp_path, ring_cameras(9, up=(0, -1, 0), height=0.5), 52, 36, 44.0, rng)
    full = D.load_dataset(tmp_path, resolution_scale=2)
    cams = D.load_dataset(tmp_path, resolution_scale=2, pixels=False)
    np.testing.assert_array_equal(full.world_from_source, cams.world_from_source)
    for split in ("train", "test"):
        a, b = getattr(full, split), getattr(cams, split)
        assert [v.name for v in a] == [v.name for v in b] and len(a) > 0
        for va, vb in zip(a, b):
            np.testing.assert_array_equal(va.camera.to_world, vb.camera.to_world)
            assert (va.camera.width, va.camera.height, va.camera.fov_x_deg,
                    va.camera.principal_point_offset_x) == (
                vb.camera.width, vb.camera.height, vb.camera.fov_x_deg,
                vb.camera.principal_point_offset_x)
            assert vb.image.shape == va.image.shape and vb.image.strides == (0, 0, 0)
            assert not vb.image.any() and vb.mask is None
    (tmp_path / "broken.png").write_bytes(b"\x89PNG not really")
    from comgs_dr.data.images import image_size
    _raises(lambda: image_size(tmp_path / "broken.png"), "broken.png", "corrupt")
