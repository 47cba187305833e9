"""Equirect panoramas of surfel scenes: coverage, analytic depths/normals, direction
convention, exclusion around the point, errors, supersampling."""
import logging

import numpy as np
import pytest

from comgs_dr.core.equirect import (
    coverage,
    equirect_dir_to_uv_np,
    equirect_uv_to_dir_np,
    pixel_directions,
)
from comgs_dr.surfels.panorama import PanoramaConfig, trace_panorama

W, H = 64, 32
CENTRE = np.array([0.1, -0.05, 0.2])


def _scene(parts):
    """gbuffer scene (no sensors) from {id: SurfelParams}."""
    from comgs_dr.surfels.scene import gbuffer_scene
    return gbuffer_scene(parts, [], targets="weight")


def _pixel_dirs(w=W, h=H):
    return pixel_directions(w, h, 0, w * h).reshape(h, w, 3)


def _sphere(radius, centre, n, subdiv=4, colour=None, seed=0):
    import trimesh

    from comgs_dr.surfels.from_mesh import from_mesh
    m = trimesh.creation.icosphere(subdivisions=subdiv, radius=radius)
    m.apply_translation(centre)
    if colour is not None:
        m.visual.vertex_colors = np.tile(np.r_[colour, 255], (len(m.vertices), 1)).astype(np.uint8)
    return from_mesh(m, n, seed=seed, opacity=0.99)


def _ground(half=2.0, n=3000, seed=1):
    import trimesh

    from comgs_dr.surfels.from_mesh import from_mesh
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], float)
    m = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    m.visual.vertex_colors = np.tile([128, 128, 128, 255], (4, 1)).astype(np.uint8)
    return from_mesh(m, n, seed=seed, opacity=0.99)


def _patch(centre, rgb, sigma=0.08):
    """One surfel at ``centre`` facing the origin, display colour ``rgb``."""
    from comgs_dr.surfels.from_mesh import frame_to_quat
    from comgs_dr.surfels.kernel import SH_C0
    c = np.asarray(centre, float)
    n = -c / np.linalg.norm(c)
    t = np.cross(n, [0, 0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0, 0])
    t /= np.linalg.norm(t)
    R = np.stack([t, np.cross(n, t), n], 1)[None]
    return dict(means=c[None], quats=frame_to_quat(R), log_scales=np.full((1, 2), np.log(sigma)),
                opacity_logit=np.full(1, 6.0), sh=((np.asarray(rgb, float) - 0.5) / SH_C0)[None])


def _patches(items):
    from comgs_dr.surfels import SurfelParams
    ds = [_patch(*it) for it in items]
    return SurfelParams.from_numpy(**{k: np.concatenate([d[k] for d in ds]) for k in ds[0]})


# ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def closed_sphere():
    R = 0.5
    scene = _scene({"sphere": _sphere(R, CENTRE, 4000)})
    return R, scene, trace_panorama(scene, CENTRE, PanoramaConfig(width=W, height=H))


def test_closed_sphere_coverage_depth_normal_colour(closed_sphere):
    from comgs_dr.core.colorspace import srgb_decode as srgb_to_linear
    from comgs_dr.core.colorspace import srgb_encode as linear_to_srgb
    R, _, out = closed_sphere
    assert out["rgb"].shape == (H, W, 3) and out["ldr"].shape == (H, W, 3)
    assert out["alpha"].shape == (H, W) and out["depth"].shape == (H, W)
    assert out["normal"].shape == (H, W, 3)
    for k in ("rgb", "ldr", "alpha", "normal", "depth"):
        assert out[k].dtype == np.float32 and np.all(np.isfinite(out[k])), k
    assert out["meta"]["coverage"] == pytest.approx(coverage(out["alpha"]))
    assert out["meta"]["coverage"] > 0.98
    # random surfel tiling leaves a few thin spots (from_mesh: mean W ≈ 0.985)
    assert out["alpha"].min() > 0.5 and np.percentile(out["alpha"], 5) > 0.9
    assert out["meta"]["position"] == pytest.approx(CENTRE.tolist())
    assert "atan2" in out["meta"]["convention"]
    # analytic depth R away from the poles (icosphere facets sit ≤ 0.3 % inside the sphere)
    rows = slice(4, H - 4)
    d = out["depth"][rows]
    assert np.abs(d - R).max() < 0.02 * R
    assert np.median(np.abs(d - R)) < 0.006 * R
    # normals face the point: n ≈ −direction, unit length
    dirs = _pixel_dirs()
    dots = -(out["normal"] * dirs).sum(-1)[rows]
    assert np.median(dots) > 0.995 and dots.min() > 0.95
    assert np.allclose(np.linalg.norm(out["normal"], axis=-1), 1.0, atol=1e-4)
    # default albedo 0.5 grey: display value srgb(0.5), linear radiance 0.5 (un-premultiplied)
    assert np.allclose(out["ldr"], linear_to_srgb(0.5), atol=0.01)
    assert np.allclose(out["rgb"], srgb_to_linear(linear_to_srgb(0.5)), atol=0.01)


def test_closed_box_depths():
    import trimesh

    from comgs_dr.surfels.from_mesh import from_mesh
    h = np.array([0.6, 0.4, 0.3])                           # half extents
    box = trimesh.creation.box(extents=2 * h)
    box.apply_translation(CENTRE)
    box.visual.vertex_colors = np.tile([200, 100, 50, 255], (len(box.vertices), 1)).astype(np.uint8)
    scene = _scene({"box": from_mesh(box, 4000, seed=3, opacity=0.99)})
    out = trace_panorama(scene, CENTRE, PanoramaConfig(width=W, height=H, colour_space="linear"))
    assert out["meta"]["coverage"] > 0.98
    dirs = _pixel_dirs()
    ref = np.min(h / np.maximum(np.abs(dirs), 1e-9), axis=-1)
    rel = np.abs(out["depth"] - ref) / ref
    assert np.median(rel) < 0.005
    assert np.percentile(rel, 95) < 0.03                    # edges/corners blend two faces
    # colour_space='linear': rgb is the field's colour itself
    assert np.allclose(out["rgb"], out["ldr"], atol=1e-6)


def test_open_ground_plane():
    p = np.array([0.2, -0.1, 0.05])
    scene = _scene({"ground": _ground()})
    out = trace_panorama(scene, p, PanoramaConfig(width=W, height=H))
    cov = out["meta"]["coverage"]
    assert 0.44 < cov <= 0.5, cov                            # W of a random tiling ≈ 0.93..1
    a = out["alpha"]
    assert abs(coverage(a > 0.5) - 0.5) < 0.02               # the lower hemisphere
    assert a[: H // 2].max() < 1e-3                          # nothing above the horizon
    assert a[H // 2 + 2:].min() > 0.5 and np.median(a[H // 2 + 2:]) > 0.9
    lower = a > 0.5
    n = out["normal"][lower]
    assert n[:, 2].min() > 0.99                              # +Z (facing the point)
    assert np.all(out["normal"][a < 1e-4] == 0) and np.all(out["depth"][a < 1e-4] == 0)
    dirs = _pixel_dirs()
    steep = dirs[..., 2] < -0.3
    ref = p[2] / -dirs[..., 2]
    assert np.allclose(out["depth"][steep], ref[steep], rtol=0.01, atol=1e-3)


def test_direction_convention():
    red, green = [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]
    parts = _patches([((1.0, 0, 0), red), ((0, 1.0, 0), green), ((-1.0, -1.0, -0.5), [0.1] * 3)])
    scene = _scene({"patches": parts})
    out = trace_panorama(scene, np.zeros(3), PanoramaConfig(width=W, height=H))
    u = (np.arange(W) + 0.5) / W
    v = (np.arange(H) + 0.5) / H
    uu, vv = np.meshgrid(u, v)
    for rgb_idx, target in ((0, (1.0, 0, 0)), (1, (0, 1.0, 0))):
        w = out["alpha"] * (out["ldr"][..., rgb_idx] > 0.9)
        assert w.sum() > 1
        uv = np.array([(w * uu).sum() / w.sum(), (w * vv).sum() / w.sum()])
        ref = equirect_dir_to_uv_np(np.array([target]))[0]
        assert np.allclose(uv, ref, atol=0.01), (uv, ref)
        assert np.allclose(equirect_uv_to_dir_np(uv[None])[0], target, atol=0.07)
        j, i = np.unravel_index(np.argmax(w), w.shape)
        assert np.dot(equirect_uv_to_dir_np(np.array([[u[i], v[j]]]))[0], target) > 0.98
    assert np.allclose(equirect_dir_to_uv_np(np.array([[1.0, 0, 0], [0, 1.0, 0]])),
                       [[0.5, 0.5], [0.25, 0.5]])


def test_exclude_radius_removes_object():
    p = np.array([0.0, 0.0, 0.2])
    ground = _ground(n=3000)
    obj = _sphere(0.15, p, 1500, subdiv=3, seed=5)
    scene = _scene({"ground": ground, "object": obj})
    cfg = PanoramaConfig(width=W, height=H)
    full = trace_panorama(scene, p, cfg)
    assert full["meta"]["coverage"] > 0.98 and full["meta"]["excluded"] == 0
    cfg.exclude_radius = 0.25
    out = trace_panorama(scene, p, cfg)
    gm = ground.to_numpy()["means"]
    near_ground = int((np.linalg.norm(gm - p, axis=1) <= 0.25).sum())
    assert near_ground > 0                                   # the object's footprint
    assert out["meta"]["excluded"] == 1500 + near_ground
    assert out["meta"]["excluded_per_shape"] == {"ground": near_ground, "object": 1500}
    assert out["meta"]["surfels"] == 3000 - near_ground
    # what is left: the ground's lower hemisphere minus the footprint hole straight down
    # (horizontal radius √(0.25² − 0.2²) = 0.15 at depth 0.2: a cone of half-angle 36.9°)
    hole = (1 - np.cos(np.arctan2(np.sqrt(0.25**2 - 0.2**2), 0.2))) / 2
    assert abs(coverage(out["alpha"] > 0.5) - (0.5 - hole)) < 0.02
    assert out["meta"]["coverage"] < full["meta"]["coverage"] - 0.5
    assert out["alpha"][: H // 2].max() < 1e-3
    # nadir: the footprint is gone (only the Gaussian tails of the ring of surfels ≥ 2.4σ
    # away remain)
    assert out["alpha"][-1].max() < 0.4
    # the original scene is untouched
    again = trace_panorama(scene, p, PanoramaConfig(width=W, height=H))
    assert np.array_equal(again["alpha"], full["alpha"])


def test_errors_and_empty(caplog):
    scene = _scene({"patches": _patches([((1.0, 0.37, 0.2), [1, 1, 1]),
                                         ((-1.0, -0.41, -0.3), [1, 1, 1])])})
    cfg = PanoramaConfig(width=W, height=H)
    with pytest.raises(ValueError, match="finite"):
        trace_panorama(scene, [0.0, np.nan, 0.0], cfg)
    with pytest.raises(ValueError, match="3 values"):
        trace_panorama(scene, [0.0, 0.0], cfg)
    with pytest.raises(ValueError, match="bounding box"):
        trace_panorama(scene, [5.0, 0.0, 0.0], cfg)
    with pytest.raises(ValueError, match="all 2 surfels"):
        trace_panorama(scene, np.zeros(3), PanoramaConfig(width=W, height=H, exclude_radius=10.0))
    for bad in (dict(supersample=0), dict(width=0), dict(colour_space="aces"),
                dict(exclude_radius=-1.0), dict(max_hits=0)):
        with pytest.raises(ValueError, match="PanoramaConfig"):
            trace_panorama(scene, np.zeros(3), PanoramaConfig(**{**dict(width=W, height=H), **bad}))
    # two tiny surfels between pixel rays: no coverage -> returned, warned
    tiny = _scene({"patches": _patches([((1.0, 0.37, 0.2), [1, 1, 1], 1e-3),
                                        ((-1.0, -0.41, -0.3), [1, 1, 1], 1e-3)])})
    with caplog.at_level(logging.WARNING, logger="comgs_dr.surfels.panorama"):
        out = trace_panorama(tiny, np.zeros(3), cfg)
    assert out["meta"]["coverage"] == 0.0
    assert np.all(out["alpha"] == 0) and np.all(out["rgb"] == 0) and np.all(out["depth"] == 0)
    assert any("nothing covers" in r.getMessage() for r in caplog.records)


def test_supersample(closed_sphere):
    R, scene, one = closed_sphere
    out = trace_panorama(scene, CENTRE, PanoramaConfig(width=W, height=H, supersample=2))
    for k in ("rgb", "ldr", "alpha", "normal", "depth"):
        assert out[k].shape == one[k].shape and np.all(np.isfinite(out[k])), k
    assert out["meta"]["supersample"] == 2
    assert out["meta"]["coverage"] == pytest.approx(one["meta"]["coverage"], abs=0.01)
    assert np.abs(out["depth"][4:-4] - R).max() < 0.02 * R
    # sub-rays stay inside their pixel: s=2 directions of pixel 0 are near its centre
    d = pixel_directions(W, H, 0, 1, 2, np.random.default_rng(0))
    assert d.shape == (4, 3)
    uv = equirect_dir_to_uv_np(d)
    assert np.all((uv[:, 0] >= 0) & (uv[:, 0] <= 1 / W)) and np.all(uv[:, 1] <= 1 / H)


def test_coverage_numpy():
    assert coverage(np.ones((8, 16))) == pytest.approx(1.0)
    half = np.zeros((8, 16))
    half[4:] = 1
    assert coverage(half) == pytest.approx(0.5)
    band = np.zeros((8, 16))
    band[0] = 1                                              # polar row: small solid angle
    assert coverage(band) < 1 / 8
    with pytest.raises(ValueError, match="H, W"):
        coverage(np.ones(5))


def test_composite_background_fills_the_sky_only_where_observed():
    """A ground plane traced from above it, plus a sky background seen over half the
    azimuths: the sky fills exactly the uncovered, observed pixels; the ground is kept."""
    from comgs_dr.surfels.panorama import composite_background
    p = np.array([0.2, -0.1, 0.05])
    out = trace_panorama(_scene({"ground": _ground()}), p, PanoramaConfig(width=W, height=H))
    sky = np.zeros((H, W, 3)) + [0.3, 0.5, 0.9]
    observed = np.zeros((H, W))
    observed[:, : W // 2] = 1.0
    res = composite_background(out, sky, observed)
    a, a0 = res["alpha"], out["alpha"]
    top = slice(0, H // 2 - 2)
    assert np.allclose(a[top, : W // 2], 1.0) and np.allclose(a[top, W // 2:], a0[top, W // 2:])
    assert np.allclose(res["ldr"][top, : W // 2], [0.3, 0.5, 0.9], atol=1e-6)
    assert np.all(res["ldr"][top, W // 2:] == 0)                 # unobserved: still a hole
    low = a0 > 0.999
    assert np.allclose(res["ldr"][low], out["ldr"][low], atol=2e-3)          # ground kept
    n = res["normal"][top, : W // 2]
    assert np.allclose(n, -_pixel_dirs()[top, : W // 2], atol=1e-5)        # facing the point
    assert res["meta"]["coverage"] > out["meta"]["coverage"] + 0.2
    bg = res["background_alpha"]                     # the background's share: open sky
    np.testing.assert_allclose(bg, observed * (1 - np.clip(a0, 0, 1)), atol=1e-6)
    np.testing.assert_allclose(a, a0 + bg, atol=1e-6)
    lin = res["rgb"][top, : W // 2]
    assert np.allclose(lin, ((np.array([0.3, 0.5, 0.9]) + 0.055) / 1.055) ** 2.4, atol=1e-4)
    with pytest.raises(ValueError, match="do not match"):
        composite_background(out, sky[:, :-1], observed)


def test_composite_background_raises_clipped_channels_to_white():
    """Where the capture saw a channel of the background clipped, the composited panorama
    holds that channel at the white level (display 1, linear 1), other channels and the
    unclipped sky unchanged; clipped but unobserved pixels stay holes."""
    from comgs_dr.surfels.panorama import composite_background
    p = np.array([0.2, -0.1, 0.05])
    out = trace_panorama(_scene({"ground": _ground()}), p, PanoramaConfig(width=W, height=H))
    sky = np.zeros((H, W, 3)) + [0.3, 0.5, 0.9]
    observed = np.zeros((H, W))
    observed[:, : W // 2] = 1.0
    clipped = np.zeros((H, W, 3))
    clipped[2:5, 10:14, 0] = 1.0                      # red clipped, observed
    clipped[2:5, 40:44, :] = 1.0                      # clipped but never observed
    clipped[6:8, 10:14, 1] = 0.4                      # below ½: not clipped
    res = composite_background(out, sky, observed, clipped)
    plain = composite_background(out, sky, observed)
    assert np.allclose(res["ldr"][2:5, 10:14], [1.0, 0.5, 0.9], atol=1e-6)
    assert np.allclose(res["rgb"][2:5, 10:14, 0], 1.0, atol=1e-6)
    assert np.allclose(res["rgb"][2:5, 10:14, 1:], plain["rgb"][2:5, 10:14, 1:])
    assert np.all(res["ldr"][2:5, 40:44] == 0)
    rest = np.ones((H, W), bool)
    rest[2:5, 10:14] = False
    assert np.array_equal(res["ldr"][rest], plain["ldr"][rest])
    with pytest.raises(ValueError, match="clipped"):
        composite_background(out, sky, observed, clipped[..., :2])
