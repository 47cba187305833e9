"""The sun's shadow map (shading.sun_shadow) against tracing each ray (surfels.trace): the
fast path must agree with the slow, obviously-right one, in the core, across the
penumbra's tilted rays, and for receivers between the sun and the object."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core.hostarray import to_jit
from comgs_dr.shading.sun_shadow import SunShadowMap


@pytest.fixture(scope="module")
def sphere_scene():
    """A surfel sphere (radius 0.3 at (0, 0, 0.45)), alone: the objects' occlusion scene."""
    import trimesh

    from comgs_dr.surfels.from_mesh import from_mesh
    from comgs_dr.surfels.scene import gbuffer_scene
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    sphere.apply_translation([0, 0, 0.45])
    params = from_mesh(sphere, 3000, seed=0, opacity=0.99)
    return gbuffer_scene({"object": params}, [], targets="weight")


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _map_vs_trace(scene, smap, x, w):
    from comgs_dr.surfels.trace import trace_visibility_np
    fast = np.asarray(smap.occlusion(to_jit(mi.Point3f, x.astype(np.float32).T),
                                     to_jit(mi.Vector3f, w.astype(np.float32).T)))
    slow, _ = trace_visibility_np(scene, x + 1e-3 * np.array([0, 0, 1.0]), w, max_hits=32,
                                  radiance=False)
    return fast, slow


def test_sun_map_matches_traced_rays_on_the_ground(sphere_scene, rng):
    d = _unit([0.6, 0.2, 0.75])
    smap = SunShadowMap(sphere_scene, d, (0, 0, 0.45), 0.35, res=256)
    assert 0.4 < smap.coverage() < 0.8              # the sphere's disk over the map's square
    m = 4000
    # ground points around the shadow (the sphere's shadow centre: -0.45 d_xy / d_z)
    centre = -0.45 * d[:2] / d[2]
    x = np.c_[centre + rng.uniform(-0.6, 0.6, (m, 2)), np.zeros(m)]
    # directions within 2° of the sun (the penumbra's rays)
    jitter = rng.normal(size=(m, 3)) * np.radians(2.0) / np.sqrt(2)
    w = _unit(d + jitter - (jitter @ d)[:, None] * d)
    fast, slow = _map_vs_trace(sphere_scene, smap, x, w)
    assert np.all(np.isfinite(fast)) and fast.min() >= 0 and fast.max() <= 1
    assert 0.1 < slow.mean() < 0.6                    # the sample sees shadow and light
    assert np.mean(np.abs(fast - slow)) < 0.005       # measured 0.0006 (silhouette texels)
    assert np.mean(np.abs(fast - slow) > 0.5) < 0.002
    assert fast.mean() == pytest.approx(slow.mean(), abs=0.005)


def test_receivers_between_the_sun_and_the_object_stay_lit(sphere_scene):
    d = _unit([0.0, 0.3, 1.0])
    smap = SunShadowMap(sphere_scene, d, (0, 0, 0.45), 0.35, res=64)
    # on the line through the sphere's centre: above the sphere (toward the sun) and below it
    x = np.array([[0, 0, 0.45]]) + np.array([[0.8], [-0.8]]) * d
    fast, slow = _map_vs_trace(sphere_scene, smap, x, np.tile(d, (2, 1)))
    assert slow[0] < 0.01 and slow[1] > 0.95         # the reference: lit above, shadowed below
    assert fast[0] < 0.01 and fast[1] > 0.95
    # rays away from the sun, or receivers beyond the map, are never occluded by it
    far = np.array([[5.0, 5.0, 0.0]])
    assert float(np.asarray(smap.occlusion(to_jit(mi.Point3f, far.astype(np.float32).T),
                                           mi.Vector3f(*map(float, d))))[0]) == 0.0
    assert float(np.asarray(smap.occlusion(mi.Point3f(0, 0, 0.0),
                                           mi.Vector3f(*map(float, -d))))[0]) == 0.0


def test_sun_map_refuses_bad_input(sphere_scene):
    with pytest.raises(ValueError, match="direction"):
        SunShadowMap(sphere_scene, (0, 0, 0), (0, 0, 0), 1.0)
    with pytest.raises(ValueError, match="radius"):
        SunShadowMap(sphere_scene, (0, 0, 1), (0, 0, 0), float("nan"))
    with pytest.raises(ValueError, match="res"):
        SunShadowMap(sphere_scene, (0, 0, 1), (0, 0, 0), 1.0, res=1)
    smap = SunShadowMap(sphere_scene, (0, 0, 1), (0, 0, 0.45), 0.35, res=8)
    with pytest.raises(RuntimeError, match="prepare"):
        smap.lookup(mi.UInt32(0), mi.Vector3f(0, 0, 1), False)
    assert dr.width(smap.T) == 64
