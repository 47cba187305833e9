"""The true light at a placement (comgs_dr.data.placement_probe): the path-traced equirect
probe keeps the package's map convention, integrates sub-pixel suns with their area, and sees
the scene's occluders."""
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles
from comgs_dr.data.placement_probe import render_probe
from comgs_dr.data.synthetic import ENVMAP_TO_WORLD
from comgs_dr.lighting.hdr import area_resize_equirect


def _scene(img, shapes=None):
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": 4},
         "env": {"type": "envmap", "bitmap": mi.Bitmap(img.astype(np.float32)),
                 "to_world": mi.ScalarTransform4f(ENVMAP_TO_WORLD.tolist())}}
    return mi.load_dict({**d, **(shapes or {})})


def _smooth_map(h, w):
    """Asymmetric in azimuth and elevation: a mirrored or rotated probe would not match."""
    d = equirect_directions(h, w)
    return np.stack([1.0 + 0.8 * d[..., 0], 1.0 + 0.6 * d[..., 1] * d[..., 2],
                     1.2 + 0.9 * d[..., 2]], -1)


def test_open_sky_probe_is_the_map_area_averaged():
    img = _smooth_map(64, 128)
    probe = render_probe(_scene(img), [0.0, 0.0, 0.0], height=16, spp_side=4)
    ref = area_resize_equirect(img, 16, 32)
    assert probe.shape == (16, 32, 3) and probe.dtype == np.float32
    assert np.abs(probe - ref).max() < 0.02 * ref.max()
    # and not its mirror image (the check above can fail on the convention)
    assert np.abs(probe - ref[:, ::-1]).max() > 0.1


@pytest.mark.parametrize("row", [40, 1])
def test_sub_pixel_sun_keeps_its_power(row):
    """A sun of one map texel (1/64 of a probe pixel, 256 strata) is integrated with its solid
    angle, not hit or missed, also next to a pole (strata uniform in θ gave it 4.2× its power
    at row 1): its pixel's power matches the map's within the stratification error."""
    h, w = 128, 256
    img = np.full((h, w, 3), 0.1)
    img[row, 77] = 5000.0
    probe = render_probe(_scene(img), [0.0, 0.0, 0.0], height=16, spp_side=16)
    dw_map, dw_probe = pixel_solid_angles(h, w), pixel_solid_angles(16, 32)
    true = (img @ LUMA * dw_map).sum()
    got = (probe.astype(np.float64) @ LUMA * dw_probe).sum()
    assert abs(got / true - 1.0) < 0.2          # 3 seeds: 0.86–1.05
    assert np.unravel_index(np.argmax(probe @ LUMA), (16, 32)) == (row // 8, 77 // 8)


def test_probe_in_a_turned_frame():
    """world_from_probe = a quarter turn about +Z: the probe is the world's probe turned by a
    quarter of its width (u = 0.5 − φ/2π: a direction at φ in the probe is at φ + 90° in the
    world, a quarter width to the left)."""
    img = _smooth_map(64, 128)
    world = render_probe(_scene(img), [0.0, 0.0, 0.0], height=16, spp_side=4)
    quarter = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    turned = render_probe(_scene(img), [0.0, 0.0, 0.0], height=16, spp_side=4,
                          world_from_probe=quarter)
    np.testing.assert_allclose(turned, np.roll(world, 8, axis=1), atol=0.02 * world.max())
    assert np.abs(turned - world).max() > 0.1


def test_occluder_hides_the_sky_above():
    """A black plane 1 unit above the point: directions up to ~60° from the zenith see it."""
    plane = {"roof": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate(
        [0.0, 0.0, 1.0]).scale(10.0), "bsdf": {"type": "diffuse", "reflectance": {
            "type": "rgb", "value": [0.0, 0.0, 0.0]}}}}
    probe = render_probe(_scene(np.ones((32, 64, 3)), plane), [0.0, 0.0, 0.0], 16, 2)
    d = equirect_directions(16, 32)
    up = d[..., 2] > np.cos(np.radians(60.0))
    assert probe[up].max() == 0.0
    assert np.allclose(probe[d[..., 2] < 0], 1.0, atol=1e-4)    # below the horizon: the map
    assert np.isfinite(probe).all()


@pytest.mark.parametrize("kw, msg", [(dict(position=[0, 0]), "3 finite"),
                                     (dict(position=[0, np.nan, 0]), "3 finite"),
                                     (dict(height=0), "height must be in"),
                                     (dict(height=5000), "height must be in"),
                                     (dict(spp_side=0), "spp_side"),
                                     (dict(world_from_probe=np.diag([1.0, 1, -1])), "rotation"),
                                     (dict(world_from_probe=np.eye(2)), "rotation")])
def test_bad_arguments_are_clear_errors(kw, msg):
    args = dict(position=[0.0, 0.0, 0.0], height=4, spp_side=1) | kw
    with pytest.raises(ValueError, match=msg):
        render_probe(_scene(np.ones((8, 16, 3))), **args)
