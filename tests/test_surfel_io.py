"""PLY / .splat import-export of surfels (comgs_dr.surfels.io)."""
import logging

import numpy as np
import pytest

import comgs_dr

plyfile = pytest.importorskip("plyfile")


@pytest.fixture(scope="module", autouse=True)
def variant():
    comgs_dr.set_variant("llvm_ad_rgb")


def _io():
    from comgs_dr.surfels import io
    return io


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def _random_params(n, degree, seed=0):
    from comgs_dr.surfels import SurfelParams
    rng = np.random.default_rng(seed)
    K = (degree + 1) ** 2
    return SurfelParams.from_numpy(
        means=rng.normal(size=(n, 3)), quats=rng.normal(size=(n, 4)),
        log_scales=rng.normal(-3, 1, (n, 2)), opacity_logit=rng.normal(size=n),
        sh=rng.normal(size=(n, K, 3)), albedo=rng.random((n, 3)),
        roughness=rng.random(n), metallic=rng.random(n))


def _write_ply(path, cols: dict, comments=(), text=False, element="vertex"):
    """Write a PLY with one element whose float32 properties are ``cols`` (name -> [N])."""
    n = len(next(iter(cols.values())))
    arr = np.empty(n, dtype=[(k, "<f4") for k in cols])
    for k, v in cols.items():
        arr[k] = v
    plyfile.PlyData([plyfile.PlyElement.describe(arr, element)], text=text,
                    comments=list(comments)).write(str(path))
    return path


def _gs_columns(n, n_scales=2, degree=0, seed=1, normals="nx"):
    """Columns of a 2DGS (2 scales) or 3DGS (3 scales) file with random content."""
    rng = np.random.default_rng(seed)
    cols = {k: rng.normal(size=n) for k in ("x", "y", "z")}
    if normals == "nx":
        cols.update({k: np.zeros(n) for k in ("nx", "ny", "nz")})
    elif normals == "normal_i":   # GS-IR
        cols.update({f"normal_{i}": rng.normal(size=n) for i in range(3)})
    for i in range(3):
        cols[f"f_dc_{i}"] = rng.normal(size=n)
    for i in range(3 * ((degree + 1) ** 2 - 1)):
        cols[f"f_rest_{i}"] = rng.normal(size=n)
    cols["opacity"] = rng.normal(size=n)
    for i in range(n_scales):
        cols[f"scale_{i}"] = rng.normal(-4, 1, n)
    for i in range(4):
        cols[f"rot_{i}"] = rng.normal(size=n)
    return cols


def _bits(a):
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


# ------------------------------------------------------------------ round trip
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_bit_exact(tmp_path, degree):
    io = _io()
    p = _random_params(37, degree, seed=degree)
    path = tmp_path / f"s{degree}.ply"
    io.save_ply(p, path)
    q, info = io.load_ply(path, return_meta=True)
    a, b = p.to_numpy(), q.to_numpy()
    for k in a:
        assert a[k].shape == b[k].shape, k
        assert np.array_equal(_bits(a[k]), _bits(b[k])), k
    assert info.layout == "comgs_dr" and info.sh_degree == degree and info.defaulted == ()
    assert info.color_space == "srgb" and info.color_space_recorded


def test_written_layout(tmp_path):
    io = _io()
    p = _random_params(5, 2)
    path = tmp_path / "s.ply"
    io.save_ply(p, path, color_space="linear")
    ply = plyfile.PlyData.read(str(path))
    v = ply["vertex"]
    names = [q.name for q in v.properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(24)]
                     + ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3",
                        "albedo_0", "albedo_1", "albedo_2", "roughness", "metallic"])
    assert all(q.val_dtype in ("f4", "float32", "float") for q in v.properties)
    d = p.to_numpy()
    # f_rest is channel-major: R coefficients 1..8, then G, then B
    rest = np.stack([v[f"f_rest_{i}"] for i in range(24)], 1)
    assert np.array_equal(rest[:, 0], d["sh"][:, 1, 0])
    assert np.array_equal(rest[:, 7], d["sh"][:, 8, 0])
    assert np.array_equal(rest[:, 8], d["sh"][:, 1, 1])
    assert np.array_equal(rest[:, 16], d["sh"][:, 1, 2])
    assert np.array_equal(v["rot_0"], d["quats"][:, 0])       # w first
    nrm = np.stack([v["nx"], v["ny"], v["nz"]], 1)
    assert np.allclose(nrm, io.quat_to_matrix(d["quats"])[:, :, 2], atol=1e-6)
    assert "comgs_dr color_space=linear" in ply.comments
    assert io.load_ply(path, return_meta=True)[1].color_space == "linear"


def test_save_refuses_bad_values(tmp_path):
    io = _io()
    from comgs_dr.surfels import SurfelParams
    d = _random_params(4, 0).to_numpy()
    d["opacity_logit"][1] = np.nan
    with pytest.raises(ValueError, match="opacity_logit"):
        io.save_ply(SurfelParams.from_numpy(**d), tmp_path / "x.ply")
    with pytest.raises(ValueError, match="color_space"):
        io.save_ply(_random_params(2, 0), tmp_path / "y.ply", color_space="aces")


# ------------------------------------------------------------------ foreign layouts
def test_2dgs_file(tmp_path, caplog):
    io = _io()
    cols = _gs_columns(20, n_scales=2, degree=1)
    path = _write_ply(tmp_path / "2dgs.ply", cols)
    with caplog.at_level(logging.WARNING, logger="comgs_dr.surfels.io"):
        p, info = io.load_ply(path, return_meta=True)
    d = p.to_numpy()
    assert info.layout == "2dgs" and info.n_scales == 2 and info.sh_degree == 1
    assert not info.color_space_recorded and info.color_space == "srgb"
    assert set(info.defaulted) == {"albedo", "roughness", "metallic"}
    assert "albedo" in caplog.text and str(path) in caplog.text
    assert np.array_equal(d["quats"][:, 0], cols["rot_0"].astype(np.float32))
    assert np.array_equal(d["log_scales"][:, 1], cols["scale_1"].astype(np.float32))
    assert np.array_equal(d["sh"][:, 2, 1], cols["f_rest_4"].astype(np.float32))   # G, coeff 2
    assert np.all(d["albedo"] == 0.5) and np.all(d["roughness"] == 0.5) and np.all(d["metallic"] == 0)


def test_ascii_ply(tmp_path):
    io = _io()
    path = _write_ply(tmp_path / "a.ply", _gs_columns(3), text=True)
    assert io.load_ply(path).count == 3


@pytest.mark.parametrize("smallest", [0, 1, 2])
def test_3dgs_file_flattened(tmp_path, smallest):
    io = _io()
    n = 16
    cols = _gs_columns(n, n_scales=3, seed=smallest)
    rng = np.random.default_rng(7)
    ls = rng.uniform(-3, -1, (n, 3))
    ls[:, smallest] = -9.0                                   # the thin axis
    for i in range(3):
        cols[f"scale_{i}"] = ls[:, i]
    path = _write_ply(tmp_path / "3dgs.ply", cols)
    p, info = io.load_ply(path, return_meta=True)
    assert info.layout == "3dgs" and info.n_scales == 3
    d = p.to_numpy()
    q_in = np.stack([cols[f"rot_{i}"] for i in range(4)], 1).astype(np.float32)
    R_in = io.quat_to_matrix(q_in)                            # [N, 3, 3], columns = axes
    R = io.quat_to_matrix(d["quats"])
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-6)      # right-handed
    # normal == the smallest axis (same sign), tangents == the kept axes with their scales
    assert np.allclose(R[:, :, 2], R_in[:, :, smallest], atol=1e-5)
    kept = [i for i in range(3) if i != smallest]
    ls32 = ls.astype(np.float32)
    for j, (col, s) in enumerate(zip((R[:, :, 0], R[:, :, 1]), d["log_scales"].T)):
        match = [np.allclose(col, R_in[:, :, k], atol=1e-5) and np.array_equal(s, ls32[:, k]) for k in kept]
        assert any(match), f"tangent {j} is not a kept axis with its scale"
    # the in-plane covariance is preserved
    S_in = np.exp(ls32.astype(np.float64)) ** 2
    S_in[:, smallest] = 0
    cov_in = np.einsum("nij,nj,nkj->nik", R_in, S_in, R_in)
    S = np.concatenate([np.exp(d["log_scales"].astype(np.float64)) ** 2, np.zeros((n, 1))], 1)
    cov = np.einsum("nij,nj,nkj->nik", R, S, R)
    assert np.allclose(cov, cov_in, rtol=1e-5, atol=1e-12)


def test_comgs_alias(tmp_path):
    """NJU-3DV/ComGS: 2 scales, albedo_0..2/metallic/roughness stored pre-sigmoid."""
    io = _io()
    cols = _gs_columns(10)
    rng = np.random.default_rng(3)
    raw = {k: rng.normal(0, 2, 10) for k in ("albedo_0", "albedo_1", "albedo_2", "metallic", "roughness")}
    path = _write_ply(tmp_path / "comgs.ply", {**cols, **raw})
    p, info = io.load_ply(path, return_meta=True)
    d = p.to_numpy()
    assert info.materials == "comgs/gs-ir" and info.defaulted == ()
    assert np.allclose(d["albedo"][:, 1], _sigmoid(raw["albedo_1"].astype(np.float32)), atol=1e-6)
    assert np.allclose(d["metallic"], _sigmoid(raw["metallic"].astype(np.float32)), atol=1e-6)
    assert np.allclose(d["roughness"], _sigmoid(raw["roughness"].astype(np.float32)), atol=1e-6)
    # override: the values are already activated
    q = io.load_ply(path, material_encoding="activated").to_numpy()
    assert np.array_equal(q["metallic"], raw["metallic"].astype(np.float32))


def test_gsir_alias(tmp_path):
    """lzhnb/GS-IR: 3 scales, normal_0..2, albedo/roughness/metallic pre-sigmoid."""
    io = _io()
    cols = _gs_columns(10, n_scales=3, normals="normal_i", degree=3)
    raw = {k: np.linspace(-3, 3, 10) for k in ("albedo_0", "albedo_1", "albedo_2", "roughness", "metallic")}
    p, info = io.load_ply(_write_ply(tmp_path / "gsir.ply", {**cols, **raw}), return_meta=True)
    d = p.to_numpy()
    assert info.layout == "3dgs" and info.sh_degree == 3 and info.materials == "comgs/gs-ir"
    assert np.allclose(d["albedo"][:, 0], _sigmoid(raw["albedo_0"]), atol=1e-6)
    assert np.allclose(d["roughness"], _sigmoid(raw["roughness"]), atol=1e-6)


def test_irgs_alias(tmp_path):
    """IRGS: base_color_0..2 -> sigmoid*0.77+0.03, roughness/metallic -> sigmoid."""
    io = _io()
    raw = {"metallic": np.linspace(-2, 2, 8), "roughness": np.linspace(-1, 3, 8),
           **{f"base_color_{i}": np.linspace(-5, 5, 8) + i for i in range(3)}}
    p, info = io.load_ply(_write_ply(tmp_path / "irgs.ply", {**_gs_columns(8), **raw}), return_meta=True)
    d = p.to_numpy()
    assert info.materials == "irgs" and info.defaulted == ()
    assert np.allclose(d["albedo"][:, 2], _sigmoid(raw["base_color_2"]) * 0.77 + 0.03, atol=1e-6)
    assert np.allclose(d["roughness"], _sigmoid(raw["roughness"]), atol=1e-6)
    assert np.allclose(d["metallic"], _sigmoid(raw["metallic"]), atol=1e-6)


def test_r3dg_alias(tmp_path, caplog):
    """R3DG: 3 scales, base_color -> sigmoid*0.77+0.03, roughness -> sigmoid*0.9+0.09, no metallic."""
    io = _io()
    raw = {"roughness": np.linspace(-4, 4, 8),
           **{f"base_color_{i}": np.linspace(-5, 5, 8) for i in range(3)},
           **{f"incidents_dc_{i}": np.zeros(8) for i in range(3)}}
    path = _write_ply(tmp_path / "r3dg.ply", {**_gs_columns(8, n_scales=3), **raw})
    with caplog.at_level(logging.WARNING, logger="comgs_dr.surfels.io"):
        p, info = io.load_ply(path, return_meta=True)
    d = p.to_numpy()
    assert info.materials == "r3dg" and info.defaulted == ("metallic",)
    assert "metallic" in caplog.text
    assert np.allclose(d["albedo"][:, 0], _sigmoid(raw["base_color_0"]) * 0.77 + 0.03, atol=1e-6)
    assert np.allclose(d["roughness"], _sigmoid(raw["roughness"]) * 0.9 + 0.09, atol=1e-6)
    assert np.all(d["metallic"] == 0) and d["albedo"].min() >= 0 and d["albedo"].max() <= 1


# ------------------------------------------------------------------ bad files
def _expect_error(path, *words):
    io = _io()
    with pytest.raises(io.SurfelFileError) as e:
        io.load_ply(path)
    msg = str(e.value)
    assert str(path) in msg, msg
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"
    assert isinstance(e.value, ValueError)
    return msg


def test_bad_not_a_ply(tmp_path):
    path = tmp_path / "junk.ply"
    path.write_bytes(b"this is not a ply file\n\x00\x01")
    _expect_error(path, "PLY")


def test_bad_truncated(tmp_path):
    path = _write_ply(tmp_path / "t.ply", _gs_columns(50))
    data = path.read_bytes()
    path.write_bytes(data[:-37])
    _expect_error(path, "truncated")


def test_bad_no_vertex_element(tmp_path):
    path = _write_ply(tmp_path / "pts.ply", _gs_columns(4), element="point")
    _expect_error(path, "'vertex'", "point")


def test_bad_missing_properties(tmp_path):
    cols = _gs_columns(4)
    del cols["opacity"], cols["rot_2"]
    _expect_error(_write_ply(tmp_path / "m.ply", cols), "opacity", "rot_2")


@pytest.mark.parametrize("prop,val", [("opacity", np.nan), ("x", np.inf), ("f_rest_3", -np.inf)])
def test_bad_non_finite(tmp_path, prop, val):
    cols = _gs_columns(9, degree=1)
    cols[prop][[2, 5]] = val
    _expect_error(_write_ply(tmp_path / "nan.ply", cols), f"'{prop}'", "2 of 9 rows")


def test_bad_material_non_finite(tmp_path):
    cols = {**_gs_columns(5), "roughness": np.array([0, np.nan, 0, 0, 0])}
    _expect_error(_write_ply(tmp_path / "r.ply", cols), "'roughness'", "1 of 5 rows")


def test_bad_zero_quaternion(tmp_path):
    cols = _gs_columns(6)
    for i in range(4):
        cols[f"rot_{i}"][4] = 0.0
    _expect_error(_write_ply(tmp_path / "q.ply", cols), "quaternion", "rot_0", "1 of 6 rows")


@pytest.mark.parametrize("m", [1, 10, 44])
def test_bad_f_rest_count(tmp_path, m):
    cols = _gs_columns(3)
    cols.update({f"f_rest_{i}": np.zeros(3) for i in range(m)})
    _expect_error(_write_ply(tmp_path / "f.ply", cols), "f_rest", f"{m} found")


def test_bad_f_rest_gap(tmp_path):
    cols = _gs_columns(3, degree=1)
    cols["f_rest_9"] = cols.pop("f_rest_4")
    _expect_error(_write_ply(tmp_path / "g.ply", cols), "f_rest")


def test_bad_zero_vertices(tmp_path):
    cols = {k: v[:0] for k, v in _gs_columns(3).items()}
    _expect_error(_write_ply(tmp_path / "z.ply", cols), "zero vertices")


def test_bad_incomplete_material(tmp_path):
    cols = {**_gs_columns(3), "albedo_0": np.zeros(3), "albedo_1": np.zeros(3)}
    _expect_error(_write_ply(tmp_path / "al.ply", cols), "albedo_2")


# ------------------------------------------------------------------ .splat
def _make_splat(pos, scales, rgb, alpha, quats):
    """Encode like antimatter15/splat convert.py (vectorised)."""
    io = _io()
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    a = np.empty(len(pos), dtype=io._SPLAT_DTYPE)
    a["pos"], a["scale"] = pos, scales
    a["rgba"] = (np.concatenate([rgb, alpha[:, None]], 1) * 255).clip(0, 255).astype(np.uint8)
    a["rot"] = (q * 128 + 128).clip(0, 255).astype(np.uint8)
    return a.tobytes()


def test_load_splat(tmp_path):
    io = _io()
    from comgs_dr.surfels.kernel import SH_C0
    rng = np.random.default_rng(5)
    n = 64
    pos = rng.normal(size=(n, 3)).astype(np.float32)
    scales = np.exp(rng.uniform(-4, -2, (n, 3))).astype(np.float32)
    thin = rng.integers(0, 3, n)
    scales[np.arange(n), thin] = 1e-4
    rgb, alpha = rng.random((n, 3)), rng.uniform(0.05, 0.95, n)
    quats = rng.normal(size=(n, 4))
    path = tmp_path / "s.splat"
    path.write_bytes(_make_splat(pos, scales, rgb, alpha, quats))
    p, info = io.load_splat(path, return_meta=True)
    d = p.to_numpy()
    assert info.layout == "splat" and d["sh"].shape == (n, 1, 3)
    assert np.array_equal(d["means"], pos)
    col = np.floor(rgb * 255) / 255
    assert np.allclose(d["sh"][:, 0] * SH_C0 + 0.5, col, atol=1e-6)
    assert np.allclose(_sigmoid(d["opacity_logit"]), np.floor(alpha * 255) / 255, atol=1e-6)
    # normal == the thin axis of the (quantised) rotation, up to 8-bit quantisation
    R_in = io.quat_to_matrix(quats)
    n_out = io.quat_to_matrix(d["quats"])[:, :, 2]
    cosang = np.abs(np.sum(n_out * R_in[np.arange(n), :, thin], 1))
    assert cosang.min() > 0.995
    assert np.allclose(np.sort(np.exp(d["log_scales"]), 1),
                       np.sort(np.delete(scales, thin + 3 * np.arange(n)).reshape(n, 2), 1), rtol=1e-6)


def test_bad_splat(tmp_path):
    io = _io()
    path = tmp_path / "bad.splat"
    path.write_bytes(b"\x00" * 40)
    with pytest.raises(io.SurfelFileError, match="multiple of 32") as e:
        io.load_splat(path)
    assert str(path) in str(e.value)
    a = np.zeros(2, dtype=io._SPLAT_DTYPE)
    a["scale"], a["rot"] = 1.0, 128                      # rot bytes 128 -> q = 0
    path.write_bytes(a.tobytes())
    with pytest.raises(io.SurfelFileError, match="quaternion"):
        io.load_splat(path)


def test_base_colour_is_the_3dgs_dc_term_and_inverts():
    """base_colour is 0.5 + SH_C0 · f_dc (by hand: f_dc 1 → 0.5 + 0.28209…), higher bands
    ignored; sh_from_base_colour inverts it; wrong shapes are errors."""
    from comgs_dr.surfels import base_colour, sh_from_base_colour
    sh = np.zeros((2, 4, 3), np.float32)
    sh[0, 0] = [1.0, 0.0, -1.0]
    sh[:, 1:] = 5.0                                   # view-dependent bands: not the base colour
    np.testing.assert_allclose(base_colour(sh), [[0.78209479, 0.5, 0.21790521], [0.5, 0.5, 0.5]],
                               atol=1e-7)
    rgb = np.array([[0.1, 0.6, 0.9], [1.2, -0.1, 0.5]], np.float32)
    back = sh_from_base_colour(rgb)
    assert back.shape == (2, 1, 3) and back.dtype == np.float32
    np.testing.assert_allclose(base_colour(back), rgb, atol=1e-6)
    with pytest.raises(ValueError, match=r"\[N, K, 3\]"):
        base_colour(np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        sh_from_base_colour(np.zeros((4, 1, 3)))
