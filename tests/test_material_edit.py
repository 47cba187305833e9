"""Material editing: spec parsing, masks (indices, boolean, box), values and errors."""
import numpy as np
import pytest

from comgs_dr.surfels.edit import MaterialEdit, edit_materials, parse_mask_spec, parse_material_spec


def test_parse_specs():
    e = parse_material_spec("albedo=0.8,0.2,0.1,roughness=0.3,metallic=1")
    assert e.albedo == (0.8, 0.2, 0.1) and e.roughness == 0.3 and e.metallic == 1.0
    e = parse_material_spec("scale=1.5,roughness=0")
    assert e.albedo_scale == (1.5,) and e.roughness == 0.0 and e.albedo is None
    for bad in ("albedo=0.8,0.2", "rough=0.3", "albedo=0.5,0.5,0.5,scale=2", "roughness=1.5",
                "metallic=a", "roughness=0.1,0.2", ""):
        with pytest.raises(ValueError):
            parse_material_spec(bad)
    with pytest.raises(ValueError, match="roughness given more than once"):
        parse_material_spec("roughness=0.3,roughness=0.9")


def test_edit_whole_object_indices_and_box(rng, tmp_path):
    from conftest import random_surfels
    p = random_surfels(rng, n=50, extent=1.0)
    d0 = p.to_numpy()
    out = edit_materials(p, MaterialEdit(albedo=(0.9, 0.1, 0.1), roughness=0.0, metallic=1.0)).to_numpy()
    assert np.allclose(out["albedo"], [0.9, 0.1, 0.1]) and np.all(out["roughness"] == 0)
    assert np.allclose(out["means"], d0["means"])                  # geometry untouched
    idx_file = tmp_path / "idx.txt"
    idx_file.write_text("1, 3 7")
    idx = parse_mask_spec(str(idx_file), p.count)
    out = edit_materials(p, MaterialEdit(albedo_scale=(2.0,)), idx).to_numpy()
    assert np.allclose(out["albedo"][[1, 3, 7]], np.clip(2 * d0["albedo"][[1, 3, 7]], 0, 1))
    rest = np.setdiff1d(np.arange(50), [1, 3, 7])
    assert np.allclose(out["albedo"][rest], d0["albedo"][rest])
    box = parse_mask_spec("box:0,-2,-2,2,2,2", p.count)
    out = edit_materials(p, MaterialEdit(metallic=0.7), box).to_numpy()
    assert np.allclose(out["metallic"][d0["means"][:, 0] >= 0], 0.7)
    assert np.allclose(out["metallic"][d0["means"][:, 0] < 0], d0["metallic"][d0["means"][:, 0] < 0])
    with pytest.raises(ValueError, match="indices"):
        idx_file.write_text("1 99")
        parse_mask_spec(str(idx_file), p.count)
    with pytest.raises(FileNotFoundError):
        parse_mask_spec(str(tmp_path / "none.npy"), p.count)
    with pytest.raises(ValueError, match="box"):
        parse_mask_spec("box:1,1,1,0,0,0", p.count)
