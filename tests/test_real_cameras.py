"""Real cameras (issue 48 item 3): full pinhole intrinsics (fx ≠ fy, principal point off
the centre, per-image) from NeRF transforms files and dataset folders, and the Mitsuba
sensors of ``comp_folder.sensor_dict``, checked against a plain K [R | t] projection."""
import json

import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core.cameras import pinhole, sensor_intrinsics
from comgs_dr.data import comp_folder
from comgs_dr.data.types import MITSUBA_FROM_OPENCV, MITSUBA_FROM_OPENGL

W, H = 64, 48
INTRINSICS = [(50.0, 50.0, 32.0, 24.0),          # centred, square pixels
              (55.0, 55.0, 20.3, 30.7),          # principal point off the centre
              (60.0, 42.0, 37.9, 17.2),          # fx ≠ fy and off the centre
              (40.0, 64.0, 28.0, 26.5)]


def _look(eye, target=(0.0, 0.0, 0.0)):
    """Mitsuba camera-to-world (+X left, +Y up, +Z forward) looking from eye at target."""
    return np.asarray(mi.ScalarTransform4f().look_at(origin=list(eye), target=list(target),
                                                      up=[0, 0, 1]).matrix, np.float64)


def _reference(to_world, K, pts):
    """The obviously-right projection: x ~ K [R | t] X (OpenCV camera, corner-origin)."""
    c2w = to_world @ MITSUBA_FROM_OPENCV
    R, C = c2w[:3, :3].T, c2w[:3, 3]
    pc = (pts - C) @ R.T                                   # OpenCV camera frame
    uv = pc @ np.asarray(K).T
    return uv[:, :2] / uv[:, 2:3], pc[:, 2]


def _K(fx, fy, cx, cy):
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def _points(to_world, n=40, seed=0):
    rng = np.random.default_rng(seed)
    c2w = to_world @ MITSUBA_FROM_OPENCV
    local = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(3, 6, n)]
    return local @ c2w[:3, :3].T + c2w[:3, 3]


@pytest.mark.parametrize("intr", INTRINSICS)
def test_sensor_rays_match_k_rt(intr):
    """A ray through pixel position (u, v) of the sensor passes through the points K [R|t]
    projects to (u, v): reprojecting a point along it lands within 1e-3 px."""
    to_world = _look([3.0, -4.0, 2.5], [0.2, 0.1, 0.3])
    pts = _points(to_world)
    uv, z = _reference(to_world, _K(*intr), pts)
    inside = (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H)
    uv = uv[inside]
    s = mi.load_dict(pinhole(to_world, W, H, *intr))
    ray, _ = s.sample_ray(0.0, 0.0, mi.Point2f(uv[:, 0] / W, uv[:, 1] / H), mi.Point2f(0.5))
    o = np.array(ray.o, np.float64).reshape(3, -1).T
    d = np.array(ray.d, np.float64).reshape(3, -1).T
    back, _ = _reference(to_world, _K(*intr), o + 4.0 * d)
    assert len(uv) >= 10
    assert np.abs(back - uv).max() < 1e-3
    assert np.allclose(sensor_intrinsics(s), intr, atol=1e-3)


def _render_spots(sensor_dict, pts, r=0.02):
    """Render small emissive spheres (black world) through the sensor: [H, W] intensity."""
    scene = {"type": "scene", "integrator": {"type": "direct"}}
    for i, p in enumerate(pts):
        scene[f"s{i}"] = {"type": "sphere", "center": list(map(float, p)), "radius": r,
                          "emitter": {"type": "area", "radiance": {"type": "rgb",
                                                                   "value": 1.0}}}
    sd = dict(sensor_dict)
    sd["sampler"] = {"type": "stratified", "sample_count": 1024}
    img = mi.render(mi.load_dict(scene), sensor=mi.load_dict(sd))
    return np.asarray(img, np.float64)[..., 0]


def _reference_coverage(to_world, K, centre, r, win, n=64):
    """Centroid of a sphere's pixel coverage in the pixels ``win`` ((x0, x1, y0, y1)),
    pixels at their centres (as the rendered image's centroid), the coverage counted with
    n² reference rays K⁻¹ (u, v, 1) per pixel in numpy (OpenCV camera frame)."""
    x0, x1, y0, y1 = win
    g = (np.arange(n) + 0.5) / n
    u = (np.arange(x0, x1)[:, None] + g).ravel()
    v = (np.arange(y0, y1)[:, None] + g).ravel()
    uu, vv = np.meshgrid(u, v)
    d = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], 1) @ np.linalg.inv(K).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c2w = to_world @ MITSUBA_FROM_OPENCV
    c = (centre - c2w[:3, 3]) @ c2w[:3, :3]              # the centre in the camera frame
    b = d @ c
    hit = b * b - (c @ c - r * r) > 0
    px, py = np.floor(uu.ravel()) + 0.5, np.floor(vv.ravel()) + 0.5
    return px[hit].mean(), py[hit].mean()


@pytest.mark.parametrize("intr", INTRINSICS[1:])
def test_render_puts_points_at_k_rt_pixels(intr):
    """Rendered through ``comp_folder.sensor_dict`` (mi.render's own film mapping), each
    small sphere's pixels have the centroid the K [R|t] rays give them (< 0.01 px; both
    counted at pixel centres, so the centroid is near, not at, the K [R|t] pixel of the
    sphere's centre)."""
    to_world = _look([0.5, -5.0, 1.0], [0.0, 0.0, 0.5])
    cam = comp_folder.camera("c", to_world, W, H, *intr)
    rng = np.random.default_rng(3)
    target = np.array([[8, 8], [W - 9, 9], [10, H - 9], [W - 10, H - 10], [W / 2, H / 2]])
    target = target + rng.uniform(-0.5, 0.5, target.shape)
    # the world points K [R|t] puts at those pixels, at depth 4..5
    c2w = to_world @ MITSUBA_FROM_OPENCV
    K = _K(*intr)
    ray_cv = np.c_[target, np.ones(len(target))] @ np.linalg.inv(K).T
    pts = (ray_cv * rng.uniform(4, 5, (len(target), 1))) @ c2w[:3, :3].T + c2w[:3, 3]
    uv, _ = _reference(to_world, K, pts)
    assert np.allclose(uv, target, atol=1e-9)
    r = 0.06
    img = _render_spots(comp_folder.sensor_dict(cam), pts, r)
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    for (u, v), p in zip(target, pts):
        win = (int(u) - 4, int(u) + 5, int(v) - 4, int(v) + 5)
        w = np.zeros_like(img)
        w[win[2]:win[3], win[0]:win[1]] = img[win[2]:win[3], win[0]:win[1]]
        cu, cv = (w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()
        ru, rv = _reference_coverage(to_world, K, p, r, win)
        assert abs(cu - ru) < 0.01 and abs(cv - rv) < 0.01, (ru, rv, cu, cv)
        assert abs(ru - u) < 0.25 and abs(rv - v) < 0.25, (u, v, ru, rv)   # pixel quantised


def _transforms(path, frames, **top):
    path.write_text(json.dumps({**top, "frames": frames}))
    return path


def _frame(name, to_world, **k):
    return {"file_path": f"./test/{name}", "transform_matrix":
            (to_world @ np.linalg.inv(MITSUBA_FROM_OPENGL)).tolist(), **k}


def test_read_cameras_full_intrinsics(tmp_path):
    """fl_x/fl_y/cx/cy/w/h top-level, overridden per frame; camera_angle_x alone."""
    m = _look([3.0, 0.0, 1.0])
    p = _transforms(tmp_path / "t.json",
                    [_frame("a", m), _frame("b", m, fl_x=70.0, cx=30.0),
                     _frame("c", m, w=128, h=96, fl_x=120.0, fl_y=100.0, cx=60.0, cy=50.0)],
                    fl_x=60.0, fl_y=42.0, cx=37.9, cy=17.2, w=W, h=H)
    a, b, c = comp_folder.read_cameras(p)
    assert (a["fx"], a["fy"], a["cx"], a["cy"], a["width"], a["height"]) == \
        (60.0, 42.0, 37.9, 17.2, W, H)
    assert (b["fx"], b["fy"], b["cx"], b["cy"]) == (70.0, 42.0, 30.0, 17.2)
    assert (c["fx"], c["fy"], c["cx"], c["cy"], c["width"]) == (120.0, 100.0, 60.0, 50.0, 128)
    assert np.allclose(a["to_world"], m)
    # --res: the same aspect rescales each axis; sizes per frame become one
    a2, _, c2 = comp_folder.read_cameras(p, res=(32, 24))
    assert np.allclose([a2["fx"], a2["fy"], a2["cx"], a2["cy"]], [30.0, 21.0, 18.95, 8.6])
    assert np.allclose([c2["fx"], c2["fy"], c2["cx"], c2["cy"]], [30.0, 25.0, 15.0, 12.5])
    # camera_angle_x alone: centred square pixels, sized when the size is known
    q = _transforms(tmp_path / "q.json", [_frame("a", m)], camera_angle_x=2 * np.arctan(0.5))
    (u,) = comp_folder.read_cameras(q)
    assert u["width"] is None
    with pytest.raises(ValueError, match="image size unknown"):
        comp_folder.sensor_dict(u)
    u = comp_folder.sized(u, 40, 20)
    assert np.allclose([u["fx"], u["fy"], u["cx"], u["cy"]], [40.0, 40.0, 20.0, 10.0])


def test_sensor_dict_reproduces_file_intrinsics(tmp_path):
    m = _look([3.0, -1.0, 1.0])
    p = _transforms(tmp_path / "t.json", [_frame("a", m)], fl_x=60.0, fl_y=42.0, cx=37.9,
                    cy=17.2, w=W, h=H)
    (a,) = comp_folder.read_cameras(p)
    s = mi.load_dict(comp_folder.sensor_dict(a))
    assert np.allclose(sensor_intrinsics(s), (60.0, 42.0, 37.9, 17.2), atol=1e-3)


@pytest.mark.parametrize("bad, match", [
    ({"fl_x": -3.0, "w": 10, "h": 10}, "invalid intrinsics|fl_x"),
    ({"fl_x": 20.0, "k1": 0.1, "w": 10, "h": 10}, "distorted"),
    ({"cx": 3.0}, "camera_angle_x' or 'fl_x"),
    ({"camera_angle_x": 4.0}, r"not in \(0, pi\)"),
    ({"fl_x": "x", "w": 10, "h": 10}, "non-numeric"),
])
def test_read_cameras_bad_intrinsics(tmp_path, bad, match):
    p = _transforms(tmp_path / "t.json", [_frame("a", np.eye(4))], **bad)
    with pytest.raises(ValueError, match=match) as e:
        comp_folder.read_cameras(p)
    assert "t.json" in str(e.value)


def test_dataset_cameras_keep_principal_point(tmp_path):
    """A NeRF-synthetic folder with per-frame cx/cy and fl_y: dataset_cameras keeps them."""
    from PIL import Image
    m = _look([3.0, 0.0, 1.0])
    (tmp_path / "test").mkdir()
    for n in ("a", "b"):
        Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(tmp_path / "test" / f"{n}.png")
    fr = [_frame("a.png", m, cx=20.0, cy=30.0), _frame("b.png", m, fl_x=70.0, fl_y=70.2)]
    for split in ("train", "test"):
        _transforms(tmp_path / f"transforms_{split}.json", fr, fl_x=50.0, w=W, h=H)
    a, b = comp_folder.dataset_cameras(tmp_path)
    assert np.allclose([a["fx"], a["fy"], a["cx"], a["cy"]], [50.0, 50.0, 20.0, 30.0])
    assert np.allclose([b["fx"], b["fy"], b["cx"], b["cy"]], [70.0, 70.2, 32.0, 24.0])
    assert comp_folder.sensor_dict(b)["type"] == "comgs_pinhole"
    s = mi.load_dict(comp_folder.sensor_dict(a))
    assert np.allclose(sensor_intrinsics(s), (50.0, 50.0, 20.0, 30.0), atol=1e-3)


@pytest.mark.parametrize("intr", INTRINSICS[:2])
def test_step1_camera_and_rasteriser_follow_k(intr):
    """Step 1's own camera (``data.types.Camera``: what ``compose`` and ``render`` use):
    its sensor's rays, its ``project`` and the surfel rasteriser's fitted projection
    (``surfels.raster.pinhole_view``) all follow K [R|t] with the principal point off the
    centre (its pixels are square: the loaders keep fx when fx, fy differ by <= 1 %)."""
    from comgs_dr.data.types import Camera
    from comgs_dr.surfels.raster import pinhole_view
    to_world = _look([3.0, -4.0, 2.5], [0.2, 0.1, 0.3])
    cam = Camera.from_intrinsics(to_world, W, H, *intr)
    pts = _points(to_world)
    uv, _ = _reference(to_world, _K(*intr), pts)
    mine, _ = cam.project(pts)
    assert np.abs(mine - uv).max() < 1e-4          # its pose re-orthonormalised
    s = mi.load_dict(cam.sensor_dict())
    assert np.allclose(sensor_intrinsics(s), intr, atol=1e-3)
    A = pinhole_view(s).A                   # Mitsuba camera plane (+X left, +Y up) → pixels
    fx, fy, cx, cy = intr
    assert np.allclose(A, [[-fx, 0, cx], [0, -fy, cy]], atol=2e-3)


def _check_rays_follow(cam):
    """The camera dict's sensor rays reproject to their pixels under its own K [R|t]."""
    K = _K(cam["fx"], cam["fy"], cam["cx"], cam["cy"])
    w, h = cam["width"], cam["height"]
    g = np.stack(np.meshgrid(np.linspace(0.5, w - 0.5, 5), np.linspace(0.5, h - 0.5, 4)),
                 -1).reshape(-1, 2)
    s = mi.load_dict(comp_folder.sensor_dict(cam))
    ray, _ = s.sample_ray(0.0, 0.0, mi.Point2f(g[:, 0] / w, g[:, 1] / h), mi.Point2f(0.5))
    o = np.array(ray.o, np.float64).reshape(3, -1).T
    d = np.array(ray.d, np.float64).reshape(3, -1).T
    back, _ = _reference(cam["to_world"], K, o + 3.0 * d)
    assert np.abs(back - g).max() < 1e-3


def test_colmap_and_llff_folders_keep_their_intrinsics(tmp_path):
    """COLMAP PINHOLE fx 22.0, fy 22.1, cx 11.4, cy 7.9 (26×18) and LLFF (focal 44 for
    52×36, files 26×18): dataset_cameras keeps each, and the sensors follow them."""
    from test_recon_data import make_colmap, ring_cameras, write_llff
    rng = np.random.default_rng(0)
    make_colmap(tmp_path / "colmap", rng)
    cams = comp_folder.dataset_cameras(tmp_path / "colmap")
    assert [c["name"] for c in cams] == ["img_00", "img_08"]
    for c in cams:
        assert np.allclose([c["fx"], c["fy"], c["cx"], c["cy"], c["width"], c["height"]],
                           [22.0, 22.1, 11.4, 7.9, 26, 18])
        assert comp_folder.sensor_dict(c)["type"] == "comgs_pinhole"
        _check_rays_follow(c)
    half = comp_folder.dataset_cameras(tmp_path / "colmap", res=(13, 9))[0]
    assert np.allclose([half["fx"], half["fy"], half["cx"], half["cy"]],
                       [11.0, 11.05, 5.7, 3.95])
    (tmp_path / "llff").mkdir()
    write_llff(tmp_path / "llff", ring_cameras(9, up=(0, -1, 0), height=0.5), 52, 36, 44.0,
               rng, folder="images_2")
    for c in comp_folder.dataset_cameras(tmp_path / "llff"):
        assert np.allclose([c["fx"], c["fy"], c["cx"], c["cy"], c["width"], c["height"]],
                           [22.0, 22.0, 13.0, 9.0, 26, 18])
        assert comp_folder.sensor_dict(c)["type"] == "perspective"
        _check_rays_follow(c)
