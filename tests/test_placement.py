"""Placement of objects: transform.json parsing and errors, similarity transform of surfels
(centres, frames, scales and SH colour) checked against applying it to the geometry."""
import json

import numpy as np
import pytest

from comgs_dr.core.hostarray import to_jit
from comgs_dr.core.similarity import euler_xyz_deg, from_entry, from_matrix, read_placements, \
    write_placements


def test_entries_round_trip_and_euler(tmp_path):
    sim = from_entry("a", {"location": [1, 2, 3], "rotation": [30, -20, 75], "scale": 2.0})
    m = sim.matrix
    again = from_matrix(m.ravel().tolist(), "a")
    assert np.allclose(again.matrix, m) and np.isclose(again.scale, 2.0)
    p = np.random.default_rng(0).normal(size=(5, 3))
    assert np.allclose(sim.inverse().points(sim.points(p)), p)
    # Blender 'XYZ': X first, then Y, then Z (world axes)
    rz90 = euler_xyz_deg(0, 0, 90)
    assert np.allclose(rz90 @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    r = euler_xyz_deg(90, 0, 90)
    assert np.allclose(r @ [0, 1, 0], euler_xyz_deg(0, 0, 90) @ (euler_xyz_deg(90, 0, 0) @ [0, 1, 0]))
    path = write_placements(tmp_path / "transform.json", {"a": sim, "b": from_entry("b", {"scale": 0.5})})
    back = read_placements(path)
    assert list(back) == ["a", "b"] and np.allclose(back["a"].matrix, m)


@pytest.mark.parametrize("entry,msg", [
    ({"transform": np.diag([1, 2, 1, 1]).ravel().tolist()}, "non-uniform"),
    ({"transform": np.diag([1, 1, -1, 1]).ravel().tolist()}, "mirror"),
    ({"transform": np.diag([0, 0, 0, 1]).ravel().tolist()}, "singular"),
    ({"transform": [float("nan")] + [0] * 15}, "non-finite"),
    ({"transform": [1, 2, 3]}, "16 numbers"),
    ({"scale": [1, 2, 1]}, "non-uniform"),
    ({"scale": -1}, "positive"),
    ({"location": [1, 2]}, "location"),
    ({"transform": np.eye(4).ravel().tolist(), "scale": 2}, "not both"),
    ({}, "no 'transform'"),
])
def test_placement_errors_name_the_object(entry, msg):
    with pytest.raises(ValueError, match=msg) as e:
        from_entry("chair", entry)
    assert "chair" in str(e.value)


def test_placement_file_errors(tmp_path):
    p = tmp_path / "t.json"
    p.write_text("{")
    with pytest.raises(ValueError, match="JSON"):
        read_placements(p)
    p.write_text(json.dumps({"mug": {"scale": [1, 1, 3]}}))
    with pytest.raises(ValueError, match="mug"):
        read_placements(p)
    with pytest.raises(FileNotFoundError):
        read_placements(tmp_path / "missing.json")


def test_transform_surfels_matches_transformed_geometry(rng):
    import drjit as dr
    import mitsuba as mi
    from conftest import random_surfels

    from comgs_dr.surfels import kernel as K
    from comgs_dr.surfels.transform import transform_surfels
    params = random_surfels(rng, n=40, sh_degree=3)
    sim = from_entry("x", {"location": [0.3, -1, 2], "rotation": [20, 40, -70], "scale": 1.7})
    out = transform_surfels(params, sim)
    a, b = params.to_numpy(), out.to_numpy()
    assert np.allclose(b["means"], sim.points(a["means"]), atol=1e-5)
    assert np.allclose(b["log_scales"], a["log_scales"] + np.log(1.7), atol=1e-6)

    def frame(p):
        tu, tv, n = K.quat_frame(to_jit(mi.Vector4f, p["quats"].T))
        return [np.asarray(v).T for v in (tu, tv, n)]
    for f0, f1 in zip(frame(a), frame(b)):
        assert np.allclose(f1, sim.directions(f0), atol=1e-5)
    # view-dependent colour: colour'(R d) = colour(d) for every surfel
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)

    def colour(p, dirs):
        basis = np.stack([np.asarray(x) for x in K.sh_basis(to_jit(mi.Vector3f, dirs.T), 3)], 1)
        return np.einsum("nk,nkc->nc", basis, p["sh"])
    assert np.allclose(colour(b, sim.directions(d)), colour(a, d), atol=1e-4)
    dr.eval()
