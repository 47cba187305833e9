"""The built-in detail stress object: a textured, UV-mapped mesh Mitsuba loads."""
import mitsuba as mi
import numpy as np

from comgs_dr.data.detail_mesh import N_RODS, detail_parts, write_detail_mesh
from comgs_dr.data.synthetic import find_texture


def test_detail_mesh_loads_with_uvs_and_texture(tmp_path):
    obj = write_detail_mesh(tmp_path)
    tex = find_texture(obj)
    assert tex is not None and tex.is_file()
    mesh = mi.load_dict({"type": "obj", "filename": str(obj)})
    params = mi.traverse(mesh)
    uv = np.asarray(params["vertex_texcoords"]).reshape(-1, 2)
    v = np.asarray(params["vertex_positions"]).reshape(-1, 3)
    assert len(uv) == len(v) and uv.min() >= 0 and uv.max() <= 1
    assert np.all(np.abs(v) <= 1.0) and v.max() > 0.85          # the cage reaches r = 0.85 + rod
    assert mesh.surface_area()[0] > 3.0                         # sphere (π) + cage + sheet
    n_parts = len(detail_parts())
    assert n_parts == 1 + N_RODS + 2 + 8 + 12                   # sphere, rods, rings, spokes, sheet
