"""core.exr (OpenEXR): round trips, layer names, metadata, channel order, chromaticities,
broken files, atomic writes; the per-view G-buffer EXRs of `comgs render` and `comgs relight`."""
import json
import os

import mitsuba as mi
import numpy as np
import OpenEXR
import pytest

from comgs_dr.core import exr

GBUFFER = {"R", "G", "B", "A", "depth.Z", "normal.X", "normal.Y", "normal.Z"}
MATERIAL = GBUFFER | {"albedo.R", "albedo.G", "albedo.B", "roughness.Y", "metallic.Y"}


def _rgba(h=12, w=20, seed=0):
    rng = np.random.default_rng(seed)
    img = rng.normal(0, 3, (h, w, 4)) * 10.0 ** rng.integers(-3, 4, (h, w, 4))
    img[0, 0] = [0.0, -0.0, 1e-7, 60000.0]
    return img.astype(np.float32)


def test_float_round_trip_is_exact(tmp_path):
    img = _rgba()
    img[1, 1, 0], img[1, 2, 1] = np.nan, np.inf                 # stored as given
    exr.write_image(tmp_path / "f.exr", img)
    back = exr.read_image(tmp_path / "f.exr")
    assert back.dtype == np.float32 and back.shape == img.shape
    np.testing.assert_array_equal(back, img)
    chans, _ = exr.read_exr(tmp_path / "f.exr")
    assert all(c.dtype == np.float32 for c in chans.values())


def test_half_round_trip_within_half_precision(tmp_path):
    img = np.clip(_rgba(), -60000, 60000)
    exr.write_image(tmp_path / "h.exr", img, pixel_type="half")
    chans, _ = exr.read_exr(tmp_path / "h.exr")
    assert set(chans) == {"R", "G", "B", "A"} and all(c.dtype == np.float16 for c in chans.values())
    back = exr.read_image(tmp_path / "h.exr")
    # half: 11 significant bits (relative rounding error <= 2^-11); subnormals below 6.1e-5
    # are spaced 2^-24 apart
    np.testing.assert_allclose(back, img, rtol=2.0 ** -11, atol=2.0 ** -25)
    assert not np.array_equal(back, img)                        # it really was rounded
    (tmp_path / "h.exr").write_bytes(b"keep")
    with pytest.raises(ValueError, match="half-float range"):
        exr.write_image(tmp_path / "h.exr", np.full((2, 2), 1e5), pixel_type="half")
    assert (tmp_path / "h.exr").read_bytes() == b"keep"


def test_layers_named_as_blender_and_read_back(tmp_path):
    rng = np.random.default_rng(1)
    h, w = 6, 9
    layers = {"": rng.random((h, w, 4)), "depth": rng.random((h, w)), "normal": rng.random((h, w, 3)),
              "albedo": rng.random((h, w, 3)), "roughness": rng.random((h, w, 1)),
              "metallic": rng.random((h, w))}
    exr.write_layers(tmp_path / "g.exr", layers)
    chans, _ = exr.read_exr(tmp_path / "g.exr")
    assert set(chans) == MATERIAL
    np.testing.assert_array_equal(chans["normal.Y"], layers["normal"][..., 1].astype(np.float32))
    np.testing.assert_array_equal(chans["depth.Z"], layers["depth"].astype(np.float32))
    back = exr.read_layers(tmp_path / "g.exr")
    assert set(back) == set(layers)
    for k, v in layers.items():
        v = v[..., None] if v.ndim == 2 else v
        np.testing.assert_array_equal(back[k], v.astype(np.float32))
    np.testing.assert_array_equal(exr.read_image(tmp_path / "g.exr"), back[""])
    with pytest.raises(ValueError, match="cannot name 2 channels"):
        exr.write_layers(tmp_path / "bad.exr", {"normal": np.zeros((2, 2, 2))})


def test_metadata_round_trip_and_envmap_layout(tmp_path):
    from comgs_dr.lighting import envmap as em
    exr.write_image(tmp_path / "m.exr", np.ones((2, 3, 3)), {"layout": "octahedral", "note": "é ü"})
    assert exr.read_attrs(tmp_path / "m.exr") == {"layout": "octahedral", "note": "é ü"}
    with pytest.raises(ValueError, match="string value"):
        exr.write_image(tmp_path / "x.exr", np.ones((2, 2)), {"layout": 3})
    with pytest.raises(ValueError, match="non-reserved"):
        exr.write_image(tmp_path / "x.exr", np.ones((2, 2)), {"compression": "none"})
    with pytest.raises(TypeError, match="use write_image"):      # an image, not channels
        exr.write_exr(tmp_path / "x.exr", np.ones((2, 2, 3)))
    oct_map = np.random.default_rng(2).random((8, 8, 3)) + 0.1      # square: needs the metadata
    em.write_exr(tmp_path / "env.exr", oct_map, "octahedral")
    arr, layout = em.read_envmap_file(tmp_path / "env.exr")
    assert layout == "octahedral" and arr.shape == (8, 8, 3)
    np.testing.assert_allclose(arr, oct_map, rtol=1e-7)
    assert "Z-up" in exr.read_attrs(tmp_path / "env.exr")["convention"]


def test_channel_order_and_naming_independent(tmp_path):
    img = _rgba(4, 5)
    for order in ("BARG", "GBAR", "ABGR"):
        chans = {c: img[..., "RGBA".index(c)].copy() for c in order}   # (the binding needs
        # contiguous arrays: it ignores strides; core.exr copies)
        OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage},
                     chans).write(str(tmp_path / f"{order}.exr"))
        np.testing.assert_array_equal(exr.read_image(tmp_path / f"{order}.exr"), img)
    # a file whose only layer is named (as some tools write) and a Y-only file
    OpenEXR.File({}, {f"Image.{c}": img[..., k].copy() for k, c in enumerate("RGB")}).write(
        str(tmp_path / "named.exr"))
    np.testing.assert_array_equal(exr.read_image(tmp_path / "named.exr"), img[..., :3])
    exr.write_image(tmp_path / "y.exr", img[..., 0])
    assert list(exr.read_exr(tmp_path / "y.exr")[0]) == ["Y"]
    np.testing.assert_array_equal(exr.read_image(tmp_path / "y.exr"), img[..., :1])
    OpenEXR.File({}, {"Z": img[..., 0].copy(), "Q": img[..., 1].copy()}).write(str(tmp_path / "z.exr"))
    with pytest.raises(ValueError, match=r"z\.exr: no RGB, RGBA or Y image.*Z, Q"):
        exr.read_image(tmp_path / "z.exr")


def test_files_from_mitsuba_and_other_primaries(tmp_path):
    """EXRs written by mi.Bitmap (older outputs) read the same; an RGB file in Rec. 2020
    primaries is converted to Rec. 709 as mi.Bitmap converts it (measured 2.8e-7)."""
    img = np.abs(_rgba(6, 8)[..., :3])
    bmp = mi.Bitmap(img)
    bmp.metadata()["layout"] = "equirect"
    bmp.write(str(tmp_path / "mi.exr"))
    np.testing.assert_array_equal(exr.read_image(tmp_path / "mi.exr"), img)
    assert exr.read_attrs(tmp_path / "mi.exr")["layout"] == "equirect"
    img = np.random.default_rng(3).random((6, 8, 3)).astype(np.float32) * 5
    rec2020 = (0.708, 0.292, 0.170, 0.797, 0.131, 0.046, 0.3127, 0.3290)
    OpenEXR.File({"chromaticities": rec2020}, {c: img[..., k].copy() for k, c in enumerate("RGB")}).write(
        str(tmp_path / "2020.exr"))
    ours = exr.read_image(tmp_path / "2020.exr")
    ref = np.asarray(mi.Bitmap(str(tmp_path / "2020.exr")))
    assert np.abs(ours - img).max() > 0.1                        # it was converted
    np.testing.assert_allclose(ours, ref, rtol=0, atol=2e-6 * np.abs(ref).max())


def test_broken_files_raise_clear_errors(tmp_path):
    from comgs_dr.lighting import envmap as em
    good = tmp_path / "good.exr"
    exr.write_layers(good, {"": _rgba(40, 24), "depth": np.ones((40, 24))})
    data = good.read_bytes()
    bad = tmp_path / "bad.exr"
    cases = [(0, "empty file"), (3, "not an OpenEXR file")]
    cases += [(n, "truncated or corrupt") for n in (4, 64, 300, len(data) // 2, len(data) - 1)]
    for n, msg in cases:
        bad.write_bytes(data[:n])
        for fn in (exr.read_image, exr.read_layers, exr.read_exr):
            with pytest.raises(ValueError, match=msg) as e:
                fn(bad)
            assert str(bad) in str(e.value), (n, str(e.value))
    bad.write_bytes(b"#?RADIANCE\n" + bytes(100))
    with pytest.raises(ValueError, match="not an OpenEXR file"):
        exr.read_image(bad)
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=f"cannot read environment map {bad}"):
        em.read_envmap_file(bad)
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        exr.read_image(tmp_path / "missing.exr")


def test_writes_are_atomic(tmp_path, monkeypatch):
    p = tmp_path / "sub" / "a.exr"
    exr.write_image(p, np.ones((3, 3, 3)))
    before = p.read_bytes()

    def fail(src, dst):
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        exr.write_image(p, np.zeros((3, 3, 3)))
    monkeypatch.undo()
    assert p.read_bytes() == before                             # the old file, untouched
    assert sorted(f.name for f in p.parent.iterdir()) == ["a.exr"]  # no temp file left
    exr.write_image(p, np.zeros((3, 3, 3)))
    assert exr.read_image(p).max() == 0 and sorted(f.name for f in p.parent.iterdir()) == ["a.exr"]


# ---------------------------------------------------------------------------------------
# G-buffer EXRs of finished runs

@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    """A 24 px, 2 + 2 view dataset of the demo object, mesh-sampled surfels of one known
    material as a finished step-1 run, and the same surfels as a step-2 (trace) material run."""
    import dataclasses

    import trimesh

    from comgs_dr.data.procedural import procedural_object, procedural_sky
    from comgs_dr.data.synthetic import ObjectDatasetConfig, make_object_dataset
    from comgs_dr.stages.decompose import MaterialConfig
    from comgs_dr.surfels import from_mesh, save_ply
    from comgs_dr.train.run import write_run_info
    root = tmp_path_factory.mktemp("exr_runs")
    mesh = procedural_object(root / "object.ply")
    sky = procedural_sky(root / "sky.exr", width=32)
    ds = root / "data"
    make_object_dataset(ObjectDatasetConfig(
        mesh=mesh, envmap=sky, out_dir=ds, n_train=2, n_test=2, resolution=24, spp=2,
        spp_aov=2, relight_envmaps=(), up_axis="z", texture=None), progress=False)
    tm = trimesh.load(mesh, force="mesh")
    tm.apply_transform(np.asarray(json.loads((ds / "meta.json").read_text())["object"]["object_to_world"]))
    run = root / "run"
    write_run_info(run, ds, "object", 1, False)
    p = from_mesh(tm, 4000, seed=0, opacity=0.99, roughness=0.4)
    d = p.to_numpy()
    d["albedo"][:] = (0.7, 0.45, 0.3)
    d["metallic"][:] = 0.25
    save_ply(type(p).from_numpy(**d), str(run / "point_cloud.ply"))
    mat = run / "material"
    mat.mkdir()
    save_ply(type(p).from_numpy(**d), str(mat / "point_cloud.ply"))
    cfg = dataclasses.asdict(MaterialConfig(visibility="trace"))
    (mat / "train_log.json").write_text(json.dumps({"summary": {"config": cfg}}))
    return run, sky


def test_render_run_writes_gbuffer_exr(tiny_runs):
    from PIL import Image

    from comgs_dr.core.colorspace import srgb_encode
    from comgs_dr.stages.render_run import render_run
    run, _ = tiny_runs
    res = render_run(run, progress=False)
    assert res["views"] == 2
    for i in range(2):
        f = run / "render_test" / f"{i:03d}.exr"
        chans, attrs = exr.read_exr(f)
        assert set(chans) == GBUFFER and "premultiplied" in attrs["colour"]
        g = exr.read_layers(f)
        a = g[""][..., 3]
        cov = a > 0.05
        assert 0.2 < (a > 0.99).mean() < 0.9 and a.min() >= 0 and a.max() <= 1 + 1e-6
        assert np.allclose(np.linalg.norm(g["normal"][cov], axis=-1), 1, atol=1e-5)
        assert (g["depth"][cov] > 0).all() and (g["depth"][a < 1e-4] == 0).all()
        assert (g[""][a < 1e-4] == 0).all()
        # linear premultiplied colour: A·sRGB(RGB/A) is the composited display colour, the
        # PNG (black background), up to its 8-bit rounding
        png = np.asarray(Image.open(run / "render_test" / f"{i:03d}_color.png"), np.float64) / 255
        enc = np.clip(a[cov, None] * srgb_encode(g[""][..., :3][cov] / a[cov, None]), 0, 1)
        assert np.abs(enc - png[cov]).max() < 0.51 / 255


def test_relight_writes_material_exr(tiny_runs):
    from comgs_dr.stages.relight import relight_run
    from comgs_dr.stages.render_run import render_run
    run, sky = tiny_runs
    r = relight_run(run, sky, rays=4, progress=False)
    assert r["views"] == 2
    out = run / "material" / f"relight_{sky.stem}_test"
    exrs = sorted(out.glob("*.exr"))
    assert len(exrs) == 2
    if not (run / "render_test" / "001.exr").exists():
        render_run(run, progress=False)
    for i, f in enumerate(exrs):
        assert set(exr.read_exr(f)[0]) == MATERIAL
        g = exr.read_layers(f)
        cov = g[""][..., 3] > 0.99
        assert cov.mean() > 0.2
        np.testing.assert_allclose(g["albedo"][cov], np.broadcast_to([0.7, 0.45, 0.3], (cov.sum(), 3)), atol=1e-5)
        np.testing.assert_allclose(g["roughness"][cov], 0.4, atol=1e-5)
        np.testing.assert_allclose(g["metallic"][cov], 0.25, atol=1e-5)
        assert np.allclose(np.linalg.norm(g["normal"][cov], axis=-1), 1, atol=1e-5)
        assert (g["albedo"][g[""][..., 3] == 0] == 0).all()
        # the same ray distance as step 1's G-buffer of the same view
        s1 = exr.read_layers(run / "render_test" / f"{i:03d}.exr")
        both = cov & (s1[""][..., 3] > 0.99)
        # (measured: median 1e-7, 99th percentile 6e-4, max 1.4e-3 relative at silhouettes)
        rel = np.abs(g["depth"][both] - s1["depth"][both]) / s1["depth"][both]
        assert both.sum() > 50 and np.median(rel) < 1e-6 and rel.max() < 3e-3
