"""Probe files, texel ray sets, farthest point sampling and automatic placement."""

import numpy as np
import pytest

from comgs_dr.core import octahedral as octa
from comgs_dr.sops.bake import texel_directions
from comgs_dr.sops.placement import PlacementConfig, farthest_points, place_probes
from comgs_dr.sops.probes import ProbeSet


def _probes(rng, p=5, r=4, tex=True):
    return ProbeSet(positions=rng.normal(size=(p, 3)), normals=np.tile([0, 0, 1.0], (p, 1)),
                    res=r, radius=0.3,
                    texture=rng.uniform(0, 1, (p, r, r, 4)) if tex else None, meta={"a": 1})


def test_probe_file_round_trip(tmp_path, rng):
    p = _probes(rng)
    path = p.save(tmp_path / "probes.npz")
    q = ProbeSet.load(path)
    assert np.array_equal(q.positions, p.positions) and np.array_equal(q.texture, p.texture)
    assert q.res == p.res and q.radius == p.radius and q.meta["a"] == 1
    # the bordered atlas round-trips through set_from_atlas
    q.set_from_atlas(q.atlas())
    assert np.array_equal(q.texture, p.texture)
    un = _probes(rng, tex=False)
    assert ProbeSet.load(un.save(tmp_path / "u.npz")).texture is None


def test_probe_errors(tmp_path, rng):
    with pytest.raises(ValueError, match="no probe"):
        ProbeSet(positions=np.zeros((0, 3)), normals=np.zeros((0, 3)), res=4, radius=1)
    with pytest.raises(ValueError, match="NaN"):
        ProbeSet(positions=[[np.nan, 0, 0]], normals=[[0, 0, 1]], res=4, radius=1)
    with pytest.raises(ValueError, match="radius"):
        ProbeSet(positions=[[0, 0, 0]], normals=[[0, 0, 1]], res=4, radius=0)
    with pytest.raises(ValueError, match="texture shape"):
        ProbeSet(positions=[[0, 0, 0]], normals=[[0, 0, 1]], res=4, radius=1,
                 texture=np.zeros((1, 4, 4, 3)))
    with pytest.raises(ValueError, match="NaN or Inf"):
        ProbeSet(positions=[[0, 0, 0]], normals=[[0, 0, 1]], res=2, radius=1,
                 texture=np.full((1, 2, 2, 4), np.inf))
    with pytest.raises(FileNotFoundError):
        ProbeSet.load(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        ProbeSet.load(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="not baked"):
        _probes(rng, tex=False).atlas()


def test_texel_directions_stay_in_their_texel():
    r, s = 8, 3
    d = texel_directions(r, s, seed=1)                             # [R²s², 3]
    assert d.shape == (r * r * s * s, 3)
    assert np.allclose(np.linalg.norm(d, axis=1), 1)
    uv = octa.dir_to_uv_np(d)
    texel = (np.minimum((uv[:, 1] * r).astype(int), r - 1) * r
             + np.minimum((uv[:, 0] * r).astype(int), r - 1))
    assert np.array_equal(texel, np.repeat(np.arange(r * r), s * s))
    assert np.allclose(texel_directions(r, 1), octa.texel_directions_np(r))
    with pytest.raises(ValueError):
        texel_directions(r, 0)


def test_farthest_points_spread_better_than_random(rng):
    pts = rng.uniform(0, 1, (20000, 3))
    idx = farthest_points(pts, 200)
    assert len(np.unique(idx)) == 200
    from scipy.spatial import cKDTree

    def covering(sel):      # largest distance from any point to the selection
        return cKDTree(pts[sel]).query(pts)[0].max()
    rand = rng.choice(len(pts), 200, replace=False)
    assert covering(idx) < 0.75 * covering(rand)
    assert np.array_equal(farthest_points(pts[:10], 50), np.arange(10))


def test_placement_on_a_surfel_sphere(rng):
    """Probes land on the fused surface, offset outwards by offset_frac × size."""
    import trimesh

    from comgs_dr.data.synthetic import look_at
    from comgs_dr.data.types import Camera
    from comgs_dr.surfels.from_mesh import from_mesh
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    params = from_mesh(sphere, 3000, seed=0, opacity=0.99)
    cams = []
    for az in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        for el in (0.3, 1.0):
            o = 2.5 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            cams.append(Camera(look_at(o), 48, 48, 40.0))
    cfg = PlacementConfig(count=300, res=8, offset_frac=0.02, min_consistent=2)
    probes = place_probes(params, cams, cfg, object_size=1.0)
    assert probes.count == 300 and probes.texture is None
    r = np.linalg.norm(probes.positions, axis=1)
    dev = np.abs(r - (0.5 + 0.02))                          # on the shell, offset outwards
    # FPS favours outliers: the few fused points at the depth tolerance (1 % of the camera
    # distance) come out first, hence the looser tail (measured 95th percentile: 0.0169 with
    # rasterised hits, which also find the coplanar hits the tracer steps over; 0.011 traced)
    assert np.median(dev) < 0.005 and np.percentile(dev, 95) < 0.02 and dev.max() < 0.06
    assert (np.sum(probes.normals * probes.positions, 1) / r > 0.9).mean() > 0.95
    assert 0.05 < probes.radius < 0.5
    assert probes.meta["placement"]["fused_points"] > 1000
    with pytest.raises(ValueError, match="no camera"):
        place_probes(params, [], cfg)
