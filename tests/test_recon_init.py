"""Initialisation helpers of reconstruction step 1."""
import types

import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core import cameras
from comgs_dr.core.hostarray import to_jit
from comgs_dr.data.types import project
from comgs_dr.train import init as I


def _cam(origin, target, w=40, h=30, fov=50.0):
    m = np.array(mi.ScalarTransform4f().look_at(origin=origin, target=target, up=[0, 0, 1]).matrix, float)
    return types.SimpleNamespace(to_world=m, width=w, height=h, fov_x_deg=fov,
                                 principal_point_offset_x=0.0, principal_point_offset_y=0.0)


def test_projection_matches_mitsuba_rays(rng):
    cam = _cam([1.0, -3.0, 1.5], [0.1, 0.2, 0.0])
    sensor = mi.load_dict(cameras.from_matrix(cam.to_world, cam.fov_x_deg, (cam.width, cam.height)))
    px = rng.uniform(0, 1, (50, 2)) * [cam.width, cam.height]
    ray, _ = sensor.sample_ray(0.0, 0.5, to_jit(mi.Point2f, (px / [cam.width, cam.height]).T),
                               mi.Point2f(0.5))
    t = rng.uniform(1, 4, 50)
    pts = np.asarray(ray.o).T + np.asarray(ray.d).T * t[:, None]
    x, y, ok = project(cam, pts)
    assert ok.all()
    np.testing.assert_allclose(np.c_[x, y], px, atol=1e-3)


def test_visual_hull_of_a_sphere(rng):
    """Masks of a sphere of radius 0.5 from 8 views: carved points lie (nearly) inside it."""
    views = []
    for az in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        o = [3 * np.cos(az), 3 * np.sin(az), 1.0]
        cam = _cam(o, [0, 0, 0], 32, 32, 40)
        yy, xx = np.mgrid[0:32, 0:32] + 0.5
        # ray-sphere test per pixel through the camera model itself
        g = np.stack([xx.ravel(), yy.ravel()], 1)
        sensor = mi.load_dict(cameras.from_matrix(cam.to_world, 40, 32))
        ray, _ = sensor.sample_ray(0.0, 0.5, to_jit(mi.Point2f, (g / 32).T), mi.Point2f(0.5))
        oo, dd = np.asarray(ray.o).T, np.asarray(ray.d).T
        b = (oo * dd).sum(1)
        disc = b * b - ((oo * oo).sum(1) - 0.25)
        mask = (disc > 0).reshape(32, 32).astype(np.float32)
        views.append(types.SimpleNamespace(camera=cam, mask=mask, image=np.full((32, 32, 3), 0.3, np.float32)))
    pts, cols = I.visual_hull_points(views, 2000, np.zeros(3), 1.5, rng)
    r = np.linalg.norm(pts, axis=1)
    assert len(pts) == 2000 and np.quantile(r, 0.95) < 0.6 and r.max() < 0.8
    np.testing.assert_allclose(cols, 0.3)
    p = I.surfels_from_points(pts, cols, rng)
    assert p.count == 2000 and np.all(np.isfinite(p.to_numpy()["log_scales"]))


def _rod_and_ball_views(n_views=12, res=40):
    """Masks (soft, 4x4 supersampled coverage) of a ball (radius 0.4 at the origin) and a thin
    rod (radius 0.015, x = 0.8, z from -0.6 to 0.6: about 0.4 px wide) seen from a ring."""
    seg = np.stack([np.full(64, 0.8), np.zeros(64), np.linspace(-0.6, 0.6, 64)], 1)
    views = []
    for az in np.linspace(0, 2 * np.pi, n_views, endpoint=False):
        cam = _cam([3 * np.cos(az), 3 * np.sin(az), 0.8], [0, 0, 0], res, res, 40)
        sensor = mi.load_dict(cameras.from_matrix(cam.to_world, 40, res))
        yy, xx = np.mgrid[0:4 * res, 0:4 * res] + 0.5
        g = np.stack([xx.ravel(), yy.ravel()], 1) / (4 * res)
        ray, _ = sensor.sample_ray(0.0, 0.5, to_jit(mi.Point2f, g.T), mi.Point2f(0.5))
        oo, dd = np.asarray(ray.o).T, np.asarray(ray.d).T
        b = (oo * dd).sum(1)
        ball = b * b - ((oo * oo).sum(1) - 0.16) > 0
        rel = seg[None] - oo[:, None]                                          # [R, 64, 3]
        perp = rel - (rel * dd[:, None]).sum(2, keepdims=True) * dd[:, None]
        rod = np.linalg.norm(perp, axis=2).min(1) < 0.015
        cover = (ball | rod).reshape(res, 4, res, 4).mean((1, 3)).astype(np.float32)
        views.append(types.SimpleNamespace(camera=cam, mask=cover,
                                           image=np.full((res, res, 3), 0.3, np.float32)))
    return views


def test_hull_rays_find_the_surface_and_thin_structures(rng):
    """Points from the pixels' rays lie on the hull's surface, and a rod 0.4 px wide gets a
    share of them; uniform volume carving almost never lands in it."""
    views = _rod_and_ball_views()
    pts, cols = I.hull_ray_points(views, 3000, np.zeros(3), 1.5, rng)
    on_rod = (np.abs(pts[:, 0] - 0.8) < 0.08) & (np.abs(pts[:, 1]) < 0.08)
    r = np.linalg.norm(pts, axis=1)
    assert len(pts) == 3000 and np.all(np.isfinite(pts))
    assert np.quantile(r[~on_rod], 0.9) < 0.56 and np.quantile(r[~on_rod], 0.1) > 0.33   # the ball's shell
    assert on_rod.mean() > 0.05, on_rod.mean()          # measured 0.09 (volume carving: 0)
    vol, _ = I.visual_hull_points(views, 3000, np.zeros(3), 1.5, rng)
    vol_rod = ((np.abs(vol[:, 0] - 0.8) < 0.08) & (np.abs(vol[:, 1]) < 0.08)).mean()
    assert vol_rod < on_rod.mean() / 3, (vol_rod, on_rod.mean())
    empty = [types.SimpleNamespace(camera=v.camera, mask=np.zeros_like(v.mask), image=v.image)
             for v in views]
    with pytest.raises(ValueError, match="every mask is empty"):
        I.hull_ray_points(empty, 100, np.zeros(3), 1.5, rng)


def test_bad_points_are_refused(rng):
    with pytest.raises(ValueError, match="finite points"):
        I.surfels_from_points(np.array([[0, 0, np.nan]] * 5), None, rng)


def test_pca_normals_of_a_sphere_shell_point_outwards(rng):
    from comgs_dr.surfels.io import quat_to_matrix
    from comgs_dr.train.init import pca_normal_quaternions
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = 0.8 * d + rng.normal(0, 0.005, d.shape) + [0.3, -0.2, 0.1]   # a thin noisy shell
    q = pca_normal_quaternions(pts)
    n = quat_to_matrix(q)[:, :, 2]
    radial = (pts - [0.3, -0.2, 0.1]) / np.linalg.norm(pts - [0.3, -0.2, 0.1], axis=1)[:, None]
    cos = (n * radial).sum(1)
    assert np.median(cos) > 0.99 and (cos > 0.9).mean() > 0.97
    assert np.allclose(np.linalg.norm(q, axis=1), 1, atol=1e-5)


def test_frustum_points_lie_where_most_cameras_look(rng):
    """Random init without masks: points of the camera-enclosing sphere that >= half of the
    views see; none beside or behind the cameras, and an error when no region is shared."""
    views = [types.SimpleNamespace(camera=_cam([3 * np.cos(a), 3 * np.sin(a), 1.0], [0, 0, 0], 32, 32, 40))
             for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    pts = I.frustum_points(views, 1500, np.zeros(3), 3.3, rng)
    assert pts.shape == (1500, 3) and pts.dtype == np.float32
    seen = sum(project(v.camera, pts)[2].astype(int) for v in views)
    assert seen.min() >= 4
    cams = np.array([v.camera.to_world[:3, 3] for v in views])
    near = np.linalg.norm(pts[:, None] - cams[None], axis=-1).min(1)
    assert near.min() > 0.7                             # none right in front of a camera
    apart = [types.SimpleNamespace(camera=_cam([3, 0, 0], [6, 0, 0], fov=10)),
             types.SimpleNamespace(camera=_cam([-3, 0, 0], [-6, 0, 0], fov=10))]
    with pytest.raises(ValueError, match="seen by"):
        I.frustum_points(apart, 100, np.zeros(3), 3.3, rng, min_seen=1.0, max_tries=2)
