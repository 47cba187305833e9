"""Synthetic object dataset generator (comgs_dr.data.synthetic) and `comgs make-dataset`.

Tiny sizes throughout (16 px, 3+3 views, 4 spp). Most tests use an icosphere PLY and
synthetic env maps written here; tests marked by ``needs_shared`` use /work/shared/data.
"""
import json
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from comgs_dr import cli
from comgs_dr.core.colorspace import srgb_encode
from comgs_dr.core.hostarray import to_jit
from comgs_dr.data import synthetic as syn

RES = 16
SHARED = syn.shared_data_dir()
needs_shared = pytest.mark.skipif(
    not (SHARED / syn.DEFAULT_MESH).is_file(),
    reason=f"shared sample data not found at {SHARED} (set $COMGS_DATA_DIR)")
BASE_COLOR = (0.3, 0.5, 0.7)


def _equirect(h, w, fn):
    """Env map image from fn(direction (h,w,3)) using the generator's Z-up orientation."""
    u, v = (np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h
    phi, th = 2 * np.pi * (0.5 - u)[None, :], np.pi * v[:, None]
    d = np.stack([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi),
                  np.cos(th) * np.ones_like(phi)], -1)
    return np.ascontiguousarray(fn(d), dtype=np.float32)


@pytest.fixture(scope="module")
def assets(tmp_path_factory, variant):
    """An icosphere PLY, a sky .hdr (RGBE) and a reddish-from-below .exr."""
    import trimesh
    d = tmp_path_factory.mktemp("assets")
    trimesh.creation.icosphere(subdivisions=2, radius=0.7).export(d / "ball.ply")
    sky = _equirect(16, 32, lambda v: np.stack([0.4 + 0.6 * np.clip(v[..., 2], 0, 1)] * 3, -1)
                    + 20.0 * (v @ np.array([0.6, 0.0, 0.8]) > 0.95)[..., None])
    mi.Bitmap(sky).write(str(d / "sky.hdr"))
    red = _equirect(16, 32, lambda v: np.stack(
        [1.5 - v[..., 2], 0.1 + 0 * v[..., 2], 0.1 + 0 * v[..., 2]], -1))
    mi.Bitmap(red).write(str(d / "red.exr"))
    return d


def _tiny_cfg(assets, out, **kw):
    base = dict(mesh=assets / "ball.ply", envmap=assets / "sky.hdr", out_dir=out,
                n_train=3, n_test=3, resolution=RES, spp=4, spp_aov=4, max_depth=3,
                relight_envmaps=(assets / "red.exr",), texture=None, base_color=BASE_COLOR)
    base.update(kw)
    return syn.ObjectDatasetConfig(**base)


@pytest.fixture(scope="module")
def tiny(assets, tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny")
    summary = syn.make_object_dataset(_tiny_cfg(assets, out), progress=False)
    meta = json.loads((out / "meta.json").read_text())
    tr = {s: json.loads((out / f"transforms_{s}.json").read_text()) for s in ("train", "test")}
    return out, summary, meta, tr


def _exr(path):
    return np.array(mi.Bitmap(str(path)), dtype=np.float32)


def _png(path):
    from PIL import Image
    return np.asarray(Image.open(path), dtype=np.float32) / 255.0


def _erode(m):
    """Pixels whose 4-neighbours are all set too."""
    e = m.copy()
    e[1:] &= m[:-1]
    e[:-1] &= m[1:]
    e[:, 1:] &= m[:, :-1]
    e[:, :-1] &= m[:, 1:]
    return e


def _pixel_rays(frame, angle_x, res):
    """World-space unit directions through pixel centres (OpenGL camera, +Y up)."""
    c2w = np.array(frame["transform_matrix"])
    s = np.tan(angle_x / 2)
    x = (2 * (np.arange(res) + 0.5) / res - 1) * s
    xx, yy = np.meshgrid(x, -x)
    d = np.stack([xx, yy, -np.ones_like(xx)], -1) @ c2w[:3, :3].T
    return c2w[:3, 3], d / np.linalg.norm(d, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------- structure

def test_files_and_json(tiny):
    out, summary, meta, tr = tiny
    assert summary["n_train"] == 3 and summary["n_test"] == 3 and summary["relight"] == ["red"]
    for split, n in (("train", 3), ("test", 3)):
        assert tr[split]["camera_angle_x"] == pytest.approx(np.radians(40.0))
        assert len(tr[split]["frames"]) == n
        for i, f in enumerate(tr[split]["frames"]):
            assert f["file_path"] == f"./{split}/r_{i}"  # no extension, as NeRF-synthetic
            assert (out / f"{split}/r_{i}.png").is_file()
            assert np.array(f["transform_matrix"]).shape == (4, 4)
    for f in tr["test"]["frames"]:
        for key in ("radiance_path", "albedo_path", "normal_path", "depth_path"):
            assert (out / f[key]).is_file(), key
        assert (out / (f["relight"]["red"] + ".png")).is_file()
        assert (out / (f["relight"]["red"] + ".exr")).is_file()
    assert meta["generator"] == syn.GENERATOR_VERSION
    assert meta["render"]["resolution"] == [RES, RES] and meta["render"]["spp_train"] == 4
    assert np.array(meta["object"]["object_to_world"]).shape == (4, 4)
    assert set(meta["relight_envmaps"]) == {"red"}
    assert "sRGB" in meta["colour_space"]["png"]


def test_object_transform_y_up_to_z_up():
    v = np.array([[0, 0, 0], [2, 4, 1]], float)  # tallest along +Y
    m, r = syn.object_transform(v, "y", half_extent=1.0)
    w = v @ m[:3, :3].T + m[:3, 3]
    assert np.allclose(w.mean(0), 0) and np.allclose(np.abs(w).max(0), [0.5, 0.25, 1.0])
    assert r == pytest.approx(np.linalg.norm([0.5, 0.25, 1.0]))


# ----------------------------------------------------------------------------- cameras

def test_cameras_on_hemisphere_looking_at_origin(tiny):
    _, summary, meta, tr = tiny
    radius = meta["cameras"]["radius"]
    assert radius == pytest.approx(summary["radius"])
    for split in ("train", "test"):
        for f in tr[split]["frames"]:
            c2w = np.array(f["transform_matrix"])
            o = c2w[:3, 3]
            assert np.linalg.norm(o) == pytest.approx(radius, rel=1e-6)
            assert o[2] >= -1e-9                                   # upper hemisphere
            forward = -c2w[:3, 2]                                  # OpenGL looks down -Z
            assert forward @ (-o / np.linalg.norm(o)) == pytest.approx(1.0, abs=1e-9)
            assert np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-9)
            assert np.allclose(np.array(f["to_world_mitsuba"]),
                               c2w @ np.diag([-1.0, 1, -1, 1]), atol=1e-12)


def test_test_views_on_three_latitude_circles():
    cams = syn.test_cameras(24, 3.0, (15.0, 35.0, 55.0))
    elev = np.array([c["elevation_deg"] for c in cams])
    assert sorted(set(elev)) == [15.0, 35.0, 55.0] and all((elev == e).sum() == 8 for e in elev)
    for e in (15.0, 35.0, 55.0):
        az = np.sort([c["azimuth_deg"] for c in cams if c["elevation_deg"] == e])
        assert np.allclose(np.diff(az), 45.0)
        z = [c["transform_matrix"][2, 3] for c in cams if c["elevation_deg"] == e]
        assert np.allclose(z, 3.0 * np.sin(np.radians(e)))


def test_transform_matrix_matches_mitsuba_image_axes(tiny):
    """Image right/up are the OpenGL +X/+Y camera axes of transform_matrix."""
    _, _, _, tr = tiny
    f = tr["test"]["frames"][1]
    c2w = np.array(f["transform_matrix"])
    sensor = mi.load_dict({"type": "perspective", "fov": 40.0,
                           "to_world": mi.ScalarTransform4f(f["to_world_mitsuba"])})
    right, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(0.9, 0.5), mi.Point2f(0.5))
    top, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(0.5, 0.1), mi.Point2f(0.5))
    assert np.array(right.d).ravel() @ c2w[:3, 0] > 0.2
    assert np.array(top.d).ravel() @ c2w[:3, 1] > 0.2


def test_envmap_orientation_is_z_up_blender_equirect(variant):
    """Mitsuba's envmap with ENVMAP_TO_WORLD returns the pixel the documented mapping names."""
    img = _equirect(64, 128, lambda d: d + 1.0)  # the pixel stores its own direction + 1
    em = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(img),
                       "to_world": mi.ScalarTransform4f(syn.ENVMAP_TO_WORLD.tolist())})
    q = np.random.default_rng(0).normal(size=(500, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    si = mi.SurfaceInteraction3f()
    si.wi = to_jit(mi.Vector3f, -q.T)
    val = np.array(em.eval(si)).reshape(3, -1).T
    assert np.abs(val - (q + 1)).max() < 0.05  # bilinear error at 128x64; mirrored: ~2


# ----------------------------------------------------------------------------- images

def test_alpha_mask_nonzero_and_not_full(tiny):
    out, _, _, tr = tiny
    for split in ("train", "test"):
        for f in tr[split]["frames"]:
            a = _png(out / (f["file_path"] + ".png"))[..., 3]
            assert a.max() == 1.0 and a.min() == 0.0
            assert 0.05 < (a > 0.5).mean() < 0.95


def test_gbuffer_normals_depth_albedo(tiny):
    out, _, meta, tr = tiny
    radius, bound = meta["cameras"]["radius"], meta["object"]["bounding_radius"]
    for f in tr["test"]["frames"]:
        nrm = _exr(out / f["normal_path"])
        dep = _exr(out / f["depth_path"]).reshape(RES, RES)
        alb = _exr(out / f["albedo_path"])
        a = nrm[..., 3]
        on, full = a > 0.5, a > 0.999
        assert np.allclose(np.linalg.norm(nrm[..., :3], axis=-1)[on], 1.0, atol=1e-4)
        assert np.all(dep[a == 0] == 0)
        assert np.all((dep[on] > radius - bound - 1e-3) & (dep[on] < radius + bound + 1e-3))
        # the sphere (radius 1 after normalisation): hit points and outward normals
        o, d = _pixel_rays(f, tr["test"]["camera_angle_x"], RES)
        p = o + dep[..., None] * d
        inner = _erode(full)  # pixel-averaged depth at the silhouette leaves the sphere
        r = np.linalg.norm(p, axis=-1)[inner]
        # faceted sphere: vertices at the bounding radius (~1), flat faces inside; the
        # pixel-averaged depth on the convex sphere overshoots slightly near the silhouette
        assert inner.sum() > 10 and np.all((r > 0.93) & (r < 1.03 * bound)), (r.min(), r.max())
        cosang = np.sum(nrm[..., :3] * p, -1)[inner] / r
        assert np.all(cosang > 0.95)
        # principled 'albedo' AOV = base colour (linear) where covered
        assert np.allclose(alb[..., :3][full], BASE_COLOR, atol=0.01)
        assert np.allclose(alb[..., 3], a)


def test_png_is_srgb_of_radiance_exr(tiny):
    out, _, _, tr = tiny
    f = tr["test"]["frames"][0]
    lin = _exr(out / f["radiance_path"])
    png = _png(out / (f["file_path"] + ".png"))
    full = lin[..., 3] > 0.999
    expect = srgb_encode(np.clip(lin[..., :3][full] / lin[..., 3:][full], 0, 1))
    assert np.abs(png[..., :3][full] - expect).max() <= 0.5 / 255 + 1e-6
    assert np.abs(png[..., 3] - lin[..., 3]).max() <= 0.5 / 255 + 1e-6


def test_relit_differs_from_base_lighting(tiny):
    out, _, _, tr = tiny
    for f in tr["test"]["frames"]:
        base = _exr(out / f["radiance_path"])
        relit = _exr(out / (f["relight"]["red"] + ".exr"))
        full = (base[..., 3] > 0.999) & (relit[..., 3] > 0.999)
        assert full.any()
        # red light from below vs grey sky: the red/blue ratio must rise clearly
        rb = lambda x: x[..., 0][full].sum() / max(x[..., 2][full].sum(), 1e-6)  # noqa: E731
        assert rb(relit) > 2.0 * rb(base)


# ----------------------------------------------------------------------------- errors

def test_bad_inputs_raise_clear_errors(assets, tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        syn.make_object_dataset(_tiny_cfg(assets, tmp_path, mesh=tmp_path / "nope.obj"), False)
    with pytest.raises(FileNotFoundError, match="nope.hdr"):
        syn.make_object_dataset(_tiny_cfg(assets, tmp_path, envmap=tmp_path / "nope.hdr"), False)
    with pytest.raises(FileNotFoundError, match="gone.exr"):
        syn.make_object_dataset(_tiny_cfg(assets, tmp_path, relight_envmaps=("gone.exr",)), False)
    junk = tmp_path / "junk.hdr"
    junk.write_bytes(b"this is not an RGBE file\n" * 8)
    with pytest.raises(ValueError, match="cannot read environment map .*junk.hdr"):
        syn.make_object_dataset(_tiny_cfg(assets, tmp_path, envmap=junk), False)
    img = np.ones((8, 16, 3), np.float32)
    img[1, 2, 0], img[3, 4, 1] = np.nan, np.inf
    mi.Bitmap(img).write(str(tmp_path / "nan.exr"))
    with pytest.raises(ValueError, match=r"nan.exr has 2 non-finite"):
        syn.make_object_dataset(_tiny_cfg(assets, tmp_path, envmap=tmp_path / "nan.exr"), False)
    for kw, name in ((dict(resolution=4), "resolution"), (dict(n_train=0), "n_train"),
                     (dict(n_test=0), "n_test"), (dict(spp=0), "spp"),
                     (dict(up_axis="x"), "up_axis")):
        with pytest.raises(ValueError, match=name):
            _tiny_cfg(assets, tmp_path, **kw)


def test_missing_default_data_is_a_clear_error(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("COMGS_DATA_DIR", str(tmp_path / "no_data"))
    with pytest.raises(FileNotFoundError, match="--mesh"):
        syn.default_mesh()
    with pytest.raises(FileNotFoundError, match="--envmap"):
        syn.default_envmap()
    assert cli.main(["make-dataset", "object", "--out", str(tmp_path / "o")]) == 2
    assert "default sample mesh" in capsys.readouterr().err


# ----------------------------------------------------------------------------- CLI

def test_cli_tiny(assets, tmp_path, capsys):
    out = tmp_path / "cli"
    code = cli.main(["make-dataset", "object", "--mesh", str(assets / "ball.ply"),
                     "--envmap", str(assets / "sky.hdr"), "--out", str(out), "--views", "2",
                     "--test-views", "3", "--res", str(RES), "--spp", "2", "--relight",
                     "--seed", "3", "--quiet", "--variant", "llvm_ad_rgb"])
    assert code == 0
    assert "wrote 2 train + 3 test views" in capsys.readouterr().out
    meta = json.loads((out / "meta.json").read_text())
    assert meta["relight_envmaps"] == {} and meta["cameras"]["seed"] == 3
    assert len(json.loads((out / "transforms_train.json").read_text())["frames"]) == 2
    assert not (out / "test_relight").exists() or not any((out / "test_relight").iterdir())
    assert cli.main(["make-dataset", "object"]) == 2        # --out is required
    assert cli.main(["make-dataset", "object", "--out", str(out), "--res", "4",
                     "--mesh", str(assets / "ball.ply")]) == 2


# ----------------------------------------------------------------------------- shared data

@needs_shared
def test_shared_envmap_split():
    assert not set(syn.TRAIN_ENVMAPS) & set(syn.HELDOUT_ENVMAPS)
    assert len(syn.TRAIN_ENVMAPS) == 4 and len(syn.HELDOUT_ENVMAPS) == 2
    assert syn.DEFAULT_ENVMAP in syn.TRAIN_ENVMAPS
    for name in syn.TRAIN_ENVMAPS + syn.HELDOUT_ENVMAPS:
        assert syn.shared_envmap(name).is_file(), name
    assert syn.find_texture(SHARED / syn.DEFAULT_MESH).name == "spot_texture.png"


@needs_shared
def test_cli_defaults_on_shared_spot(tmp_path):
    """Omitted --mesh/--envmap/--relight: Spot, a training map, the held-out maps."""
    out = tmp_path / "spot"
    assert cli.main(["make-dataset", "object", "--out", str(out), "--views", "2",
                     "--test-views", "3", "--res", str(RES), "--spp", "2", "--quiet"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert Path(meta["envmap"]).name in syn.TRAIN_ENVMAPS
    assert Path(meta["texture"]).name == "spot_texture.png"
    assert sorted(Path(p).name for p in meta["relight_envmaps"].values()) == \
        sorted(syn.HELDOUT_ENVMAPS)
    for name in meta["relight_envmaps"]:
        assert (out / f"test_relight/{name}/r_2.png").is_file()
