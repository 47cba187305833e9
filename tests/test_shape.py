"""The `surfels` shape: XML loading, parameter exposure, resizing, degenerate surfels."""
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import error_chain_text, random_surfels

from comgs_dr.core import cameras
from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels import SurfelParams, save_ply
from comgs_dr.surfels.scene import gbuffer_scene
from comgs_dr.surfels.shape import ensure_proxies, is_surfel_shape

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
XML = os.path.join(ROOT, "scenes", "gbuffer_object.xml")
FIELDS = ("means", "quats", "log_scales", "opacity_logit", "sh", "albedo", "roughness", "metallic")


def test_xml_scene_renders_all_targets(tmp_path, rng):
    ply = tmp_path / "obj.ply"
    save_ply(random_surfels(rng, n=200, extent=0.6, scale=(0.08, 0.2)), str(ply))
    scene = mi.load_file(XML, filename=str(ply), res=16)
    assert is_surfel_shape(scene.shapes()[0])
    integ = scene.integrator()
    img = mi.render(scene)
    parts = integ.split(img)
    assert set(parts) == {"color", "weight", "depth", "depth_unbiased", "normal", "albedo",
                          "roughness", "metallic"}
    W = np.array(parts["weight"])[..., 0]
    assert 0 < W.max() <= 1 + 1e-5 and (W > 0.5).mean() > 0.1
    for k, v in parts.items():
        assert np.all(np.isfinite(np.array(v))), k
    n = np.array(parts["normal"])[W > 0.9]
    assert np.all(np.linalg.norm(n, axis=-1) <= 1 + 1e-4)


def test_xml_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(Exception) as ei:
        mi.load_file(XML, filename=str(tmp_path / "nope.ply"), res=8)
    assert "nope.ply" in error_chain_text(ei.value) and "not found" in error_chain_text(ei.value)


def test_parameters_are_exposed_and_differentiable(rng):
    scene = gbuffer_scene({"obj": random_surfels(rng, n=20)}, cameras.perspective([0, -3, 0], res=8))
    params = mi.traverse(scene)
    for f in FIELDS:
        key = f"obj.{f}"
        assert key in params and not (params.flags(key) & mi.ParamFlags.NonDifferentiable)
    assert "obj.vertex_positions" not in params      # the proxy mesh is internal


def test_update_moves_geometry_and_changes_count(rng):
    p1 = random_surfels(rng, n=30)
    scene = gbuffer_scene({"obj": p1}, cameras.perspective([0, -3, 0], res=16), targets="weight")
    params = mi.traverse(scene)
    w1 = np.array(mi.render(scene))[..., 3]
    shape = scene.shapes()[0]
    # move everything out of view: the weight vanishes (BVH rebuilt)
    params["obj.means"] = p1.means + mi.Vector3f(0, 0, 50)
    params.update()
    assert np.array(mi.render(scene))[..., 3].max() == 0 and w1.max() > 0
    # a new surfel count through mi.traverse
    p2 = random_surfels(rng, n=75)
    for f in FIELDS:
        params[f"obj.{f}"] = getattr(p2, f)
    params.update()
    # proxies and BVH are rebuilt lazily, before the next trace (rasterised renders skip it)
    assert shape.surfel_count() == 75 and shape.proxies_stale
    ensure_proxies(scene, [shape])
    assert shape.face_count() == 150 and shape.vertex_count() == 300 and not shape.proxies_stale
    assert np.array(mi.render(scene))[..., 3].max() > 0
    # inconsistent counts are refused with the parameter named
    params["obj.opacity_logit"] = to_jit(mi.Float, np.zeros(10, np.float32))
    with pytest.raises(Exception) as ei:
        params.update()
    assert "has 75 entries but 'opacity_logit' has 10" in error_chain_text(ei.value)


def test_to_world_places_surfels(tmp_path, rng):
    """A similarity to_world places the surfels as transform_surfels does; a non-uniform
    scale is refused with the shape named."""
    from comgs_dr.core.similarity import Similarity, euler_xyz_deg
    from comgs_dr.surfels.transform import transform_surfels
    ply = tmp_path / "o.ply"
    p = random_surfels(rng, n=5)
    save_ply(p, str(ply))
    m = Similarity(2.0, euler_xyz_deg(10, 20, 30), np.array([1.0, -2.0, 0.5])).matrix
    sh = mi.load_dict({"type": "surfels", "filename": str(ply),
                       "to_world": mi.ScalarTransform4f(m.tolist())})
    from comgs_dr.surfels import load_ply
    want = transform_surfels(load_ply(str(ply)), Similarity(2.0, m[:3, :3] / 2, m[:3, 3]))
    np.testing.assert_allclose(np.asarray(sh.params.means), np.asarray(want.means), atol=1e-5)
    np.testing.assert_allclose(np.asarray(sh.params.log_scales),
                               np.asarray(want.log_scales), atol=1e-5)
    bad = np.diag([1.0, 2.0, 1.0, 1.0])
    with pytest.raises(Exception) as ei:
        mi.load_dict({"type": "surfels", "id": "cow", "filename": str(ply),
                      "to_world": mi.ScalarTransform4f(bad.tolist())})
    assert "cow" in error_chain_text(ei.value) and "scale" in error_chain_text(ei.value)


def _degenerate_params(rng):
    p = random_surfels(rng, n=12, extent=0.2, scale=(0.2, 0.4), opacity=(1, 2)).to_numpy()
    p["quats"][0] = 0.0                      # zero quaternion -> identity frame
    p["log_scales"][1] = [-60.0, 0.0]        # collapsed axis
    p["log_scales"][2] = [80.0, 80.0]        # huge (clamped to e^12)
    p["opacity_logit"][3] = 1e4              # saturated
    p["opacity_logit"][4] = -1e4             # invisible
    p["means"][5] = np.nan                   # NaN geometry
    p["sh"][6, 0, 1] = np.inf                # Inf colour
    p["albedo"][7] = np.nan                  # NaN material
    return SurfelParams.from_numpy(**p)


def test_degenerate_surfels_give_finite_buffers_and_gradients(rng):
    params = _degenerate_params(rng)
    scene = gbuffer_scene({"obj": params}, cameras.perspective([0, -2, 0.1], res=16, fov=60),
                                  max_hits=16)
    assert scene.shapes()[0].nonfinite_count == 3
    mp = mi.traverse(scene)
    img = mi.render(scene)
    assert np.all(np.isfinite(np.array(img)))
    assert np.array(scene.integrator().split(img)["weight"]).max() > 0.5
    for f in FIELDS:
        dr.enable_grad(mp[f"obj.{f}"])
    mp.update()
    dr.backward(dr.sum(mi.render(scene, mp), axis=None))
    for f in FIELDS:
        g = np.array(dr.grad(mp[f"obj.{f}"]))
        assert np.all(np.isfinite(g)), f


def test_surfel_shape_without_data_is_a_clear_error():
    from comgs_dr.surfels.shape import shape_class
    with pytest.raises(ValueError, match="filename"):
        shape_class()(mi.Properties("surfels"))
