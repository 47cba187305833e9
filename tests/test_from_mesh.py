"""Surfels sampled on meshes (comgs_dr.surfels.from_mesh).

``python tests/test_from_mesh.py`` regenerates the flat-plane coverage numbers quoted
at ``from_mesh.TILING``.
"""
import logging
import os

import numpy as np
import pytest

import comgs_dr
from comgs_dr.core.hostarray import to_jit

trimesh = pytest.importorskip("trimesh")
from comgs_dr.data.synthetic import shared_data_dir  # noqa: E402

MESHES = str(shared_data_dir() / "meshes")
needs_meshes = pytest.mark.skipif(not os.path.isdir(MESHES), reason=f"shared sample meshes not found at {MESHES}")


@pytest.fixture(scope="module", autouse=True)
def variant():
    comgs_dr.set_variant("llvm_ad_rgb")


def _fm():
    from comgs_dr.core.colorspace import srgb_decode, srgb_encode
    from comgs_dr.surfels import from_mesh as fm_fn  # the function (surfels/__init__)
    from comgs_dr.surfels import io
    from comgs_dr.surfels.from_mesh import TILING
    return fm_fn, io, TILING, lambda x: srgb_encode(np.clip(x, 0, 1)), srgb_decode


def _unequal_mesh():
    """Disjoint triangles with areas spanning 3 decades."""
    areas = np.array([0.01, 0.05, 0.2, 1.0, 3.0, 10.0])
    V, F = [], []
    for i, a in enumerate(areas):
        s = np.sqrt(2 * a)                                  # right triangle, legs s
        V += [[3.0 * i, 0, 0], [3.0 * i + s, 0, 0], [3.0 * i, s, 0.1 * i]]
        F.append([3 * i, 3 * i + 1, 3 * i + 2])
    return trimesh.Trimesh(np.array(V), np.array(F), process=False)


# ------------------------------------------------------------------ basics
def test_counts_and_constants():
    from_mesh, io, TILING, *_ = _fm()
    m = trimesh.creation.icosphere(subdivisions=2)
    p = from_mesh(m, 500, sh_degree=2, opacity=0.8, roughness=0.3, metallic=0.7, scale_factor=2.0)
    d = p.to_numpy()
    assert p.count == 500 and d["sh"].shape == (500, 9, 3)
    assert np.all(d["sh"][:, 1:] == 0)
    assert np.allclose(1 / (1 + np.exp(-d["opacity_logit"])), 0.8, atol=1e-6)
    assert np.all(d["roughness"] == np.float32(0.3)) and np.all(d["metallic"] == np.float32(0.7))
    sigma = 2.0 * np.sqrt(m.area / (500 * np.pi)) * TILING
    assert np.allclose(np.exp(d["log_scales"]), sigma, rtol=1e-6)


def test_seed_determinism():
    from_mesh, *_ = _fm()
    m = trimesh.creation.box()
    a = from_mesh(m, 64, seed=3).to_numpy()["means"]
    b = from_mesh(m, 64, seed=3).to_numpy()["means"]
    c = from_mesh(m, 64, seed=4).to_numpy()["means"]
    assert np.array_equal(a, b) and not np.array_equal(a, c)


@needs_meshes
def test_frames_match_faces():
    from_mesh, io, *_ = _fm()
    m = trimesh.load(os.path.join(MESHES, "suzanne.obj"))
    p, info = from_mesh(m, 2000, seed=1, return_info=True)
    d = p.to_numpy()
    R = io.quat_to_matrix(d["quats"])                       # [N, 3, 3]
    nq = np.linalg.norm(d["quats"], axis=1)
    assert np.allclose(nq, 1.0, atol=1e-6)
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-5)
    n = R[:, :, 2]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    assert np.allclose(n, m.face_normals[info.face_index], atol=1e-5)
    tri = m.triangles[info.face_index]                      # [N, 3, 3]
    e = tri[:, 1] - tri[:, 0]
    assert np.allclose(R[:, :, 0], e / np.linalg.norm(e, axis=1, keepdims=True), atol=1e-5)
    # positions: inside their triangle, on its plane
    assert info.barycentric.min() >= 0 and np.allclose(info.barycentric.sum(1), 1)
    assert np.allclose(np.einsum("nk,nkj->nj", info.barycentric, tri), d["means"], atol=1e-5)
    assert np.abs(np.sum((d["means"] - tri[:, 0]) * n, 1)).max() < 1e-5


def test_area_weighting_chi2():
    """Per-face counts vs area fractions (chi-square, 6 faces with areas 0.01..10)."""
    from scipy import stats
    from_mesh, *_ = _fm()
    m = _unequal_mesh()
    n = 20000
    _, info = from_mesh(m, n, seed=11, return_info=True)
    counts = np.bincount(info.face_index, minlength=len(m.faces))
    expected = n * m.area_faces / m.area
    _, pval = stats.chisquare(counts, expected)
    assert pval > 1e-3, (counts, expected)
    # uniform inside each triangle: E[barycentric] = 1/3 each, ± 4 standard errors (sd ≈ 0.236)
    assert np.allclose(info.barycentric.mean(0), 1 / 3, atol=4 * 0.236 / np.sqrt(n))


def test_scene_input_area_split():
    from_mesh, *_ = _fm()
    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(2, 2, 2))
    b.apply_translation([10, 0, 0])
    sc = trimesh.Scene([a, b])
    p = from_mesh(sc, 5000, seed=2)
    x = p.to_numpy()["means"][:, 0]
    frac_b = np.mean(x > 5)                                  # area ratio 24 / 30 = 0.8
    assert abs(frac_b - 0.8) < 4 * np.sqrt(0.8 * 0.2 / 5000)


# ------------------------------------------------------------------ albedo
@needs_meshes
def test_albedo_from_spot_texture():
    from_mesh, _, _, linear_to_srgb, _ = _fm()
    from comgs_dr.surfels.kernel import SH_C0
    p, info = from_mesh(os.path.join(MESHES, "spot_triangulated.obj"), 3000, seed=0,
                        texture=os.path.join(MESHES, "spot_texture.png"), return_info=True)
    d = p.to_numpy()
    a = d["albedo"]
    assert info.albedo_source == ["texture"]
    assert a.min() >= 0 and a.max() <= 1
    assert a.std(0).min() > 0.1                              # not a constant grey
    assert np.abs(a - 0.5).max() > 0.3
    assert np.allclose(d["sh"][:, 0] * SH_C0 + 0.5, linear_to_srgb(a), atol=1e-5)


@needs_meshes
def test_spot_without_texture_is_grey(caplog):
    """An OBJ without mtllib gets trimesh's placeholder material: reported, albedo 0.5."""
    from_mesh, *_ = _fm()
    with caplog.at_level(logging.WARNING, logger="comgs_dr.surfels.from_mesh"):
        p, info = from_mesh(os.path.join(MESHES, "spot_triangulated.obj"), 50, return_info=True)
    assert info.albedo_source == ["default"] and "grey" in caplog.text
    assert np.all(p.to_numpy()["albedo"] == 0.5)


def test_texture_lookup_orientation():
    """A quad with uv = xy; the top half of the image (v > 0.5) is red, the bottom blue."""
    from PIL import Image
    from_mesh, *_ = _fm()
    img = np.zeros((8, 8, 3), np.uint8)
    img[:4, :, 0] = 255                                      # image rows 0..3 = top = v in (0.5, 1]
    img[4:, :, 2] = 255
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    vis = trimesh.visual.TextureVisuals(uv=V[:, :2], image=Image.fromarray(img))
    m = trimesh.Trimesh(V, F, visual=vis, process=False)
    p = from_mesh(m, 2000, seed=5)
    d = p.to_numpy()
    y = d["means"][:, 1]
    top, bottom = (y > 0.6) & (y < 0.9), (y > 0.1) & (y < 0.4)
    assert np.allclose(d["albedo"][top], [1, 0, 0], atol=1e-6)
    assert np.allclose(d["albedo"][bottom], [0, 0, 1], atol=1e-6)


def test_vertex_and_face_colours():
    from_mesh, _, _, _, srgb_to_linear = _fm()
    m = trimesh.creation.box()
    m.visual.vertex_colors = np.tile([200, 100, 50, 255], (len(m.vertices), 1)).astype(np.uint8)
    p, info = from_mesh(m, 100, return_info=True)
    assert info.albedo_source == ["vertex_colors"]
    assert np.allclose(p.to_numpy()["albedo"], srgb_to_linear(np.array([200, 100, 50]) / 255), atol=1e-6)
    m2 = trimesh.creation.box()
    fc = np.zeros((len(m2.faces), 4), np.uint8)
    fc[:, 3] = 255
    fc[:, 1] = np.where(np.arange(len(m2.faces)) % 2 == 0, 255, 0)
    m2.visual.face_colors = fc
    p2, info2 = from_mesh(m2, 200, return_info=True)
    assert info2.albedo_source == ["face_colors"]
    g = p2.to_numpy()["albedo"][:, 1]
    assert np.array_equal(g == 1.0, info2.face_index % 2 == 0)


# ------------------------------------------------------------------ errors
def test_errors(tmp_path):
    from_mesh, *_ = _fm()
    box = trimesh.creation.box()
    with pytest.raises(ValueError, match="n must be"):
        from_mesh(box, 0)
    with pytest.raises(TypeError, match="integer"):
        from_mesh(box, 2.5)
    with pytest.raises(ValueError, match="opacity"):
        from_mesh(box, 10, opacity=1.0)
    with pytest.raises(ValueError, match="roughness"):
        from_mesh(box, 10, roughness=1.5)
    with pytest.raises(ValueError, match="SH degree"):
        from_mesh(box, 10, sh_degree=4)
    with pytest.raises(ValueError, match="no triangles"):
        from_mesh(trimesh.Trimesh(), 10)
    flat = trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float), np.array([[0, 1, 2]]),
                           process=False)
    with pytest.raises(ValueError, match="degenerate"):
        from_mesh(flat, 10)
    with pytest.raises(FileNotFoundError):
        from_mesh(tmp_path / "nope.obj", 10)
    with pytest.raises(TypeError, match="trimesh"):
        from_mesh(np.zeros((3, 3)), 10)


@needs_meshes
def test_loads_meshes_from_paths():
    from_mesh, *_ = _fm()
    for name in ("teapot.obj", "suzanne.obj"):
        p = from_mesh(os.path.join(MESHES, name), 200)
        assert p.count == 200 and np.isfinite(p.to_numpy()["means"]).all()


# ------------------------------------------------------------------ coverage by rendering
def _render_coverage(tm, n, seed=1, res=48):
    """(mean surfel weight over pixels fully inside the mesh silhouette, #pixels)."""
    import mitsuba as mi

    from comgs_dr.surfels import SurfelShapeBase
    from_mesh, *_ = _fm()
    p = from_mesh(tm, n, seed=seed)

    def sensor(fmt):
        return {"type": "perspective", "fov": 40,
                "to_world": mi.ScalarTransform4f().look_at(origin=[0.3, -4.5, 1.0], target=[0, 0, 0], up=[0, 0, 1]),
                "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                         "pixel_format": fmt},
                "sampler": {"type": "independent", "sample_count": 16}}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "surfel_gbuffer", "targets": "weight"},
                          "sensor": sensor("rgb"), "s": SurfelShapeBase.from_params(p)})
    W = np.asarray(mi.render(scene, spp=16))[:, :, -1]       # [H, W] weight AOV
    mesh = mi.Mesh("m", len(tm.vertices), len(tm.faces))
    mp = mi.traverse(mesh)
    mp["vertex_positions"] = to_jit(mi.Float, np.asarray(tm.vertices).ravel())
    mp["faces"] = to_jit(mi.UInt32, np.asarray(tm.faces).ravel())
    mp.update()
    mscene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                           "sensor": sensor("rgba"), "m": mesh})
    A = np.asarray(mi.render(mscene, spp=16))[:, :, 3]       # fraction of samples hitting the mesh
    inside = A >= 0.999
    return float(W[inside].mean()), int(inside.sum()), float(W[A == 0].mean())


def test_coverage_icosphere():
    tm = trimesh.creation.icosphere(subdivisions=3)
    mean_w, npx, outside = _render_coverage(tm, 3000)
    assert npx > 300
    assert mean_w >= 0.95, mean_w
    assert outside < 0.01


@needs_meshes
def test_coverage_suzanne():
    """Flat faces put many exactly coplanar surfels on one plane: the tracer must find
    each of them (proxy depth jitter in the `surfels` shape), else coverage drops to ~0.8."""
    tm = trimesh.load(os.path.join(MESHES, "suzanne.obj"))
    tm.apply_translation(-tm.bounds.mean(0))
    tm.apply_scale(2.0 / np.max(tm.extents))
    mean_w, npx, _ = _render_coverage(tm, 3000)
    assert npx > 100
    assert mean_w >= 0.95, mean_w


# ------------------------------------------------------------------ reference numbers
def coverage_sim(tilings=(1.0, 1.2, 1.4, 1.5, 1.6, 1.8), opacity=0.95, trials=20, seed=0):
    """Flat plane, N i.i.d. uniform surfels, density 1: mean W at random points per TILING."""
    from comgs_dr.surfels.kernel import ALPHA_MAX, ALPHA_MIN
    rng = np.random.default_rng(seed)
    L = 30.0
    out = {}
    for c in tilings:
        sig, ws = c * np.sqrt(1 / np.pi), []
        for _ in range(trials):
            P = rng.uniform(0, L, (int(L * L), 2))
            X = rng.uniform(L / 3, 2 * L / 3, (500, 2))         # away from the borders
            d2 = ((X[:, None] - P[None]) ** 2).sum(-1) / sig ** 2
            a = np.minimum(opacity * np.exp(-0.5 * d2), ALPHA_MAX)
            a = np.where(a >= ALPHA_MIN, a, 0.0)
            ws.append(1 - np.prod(1 - a, 1))
        out[c] = float(np.concatenate(ws).mean())
    return out


if __name__ == "__main__":
    for c, w in coverage_sim().items():
        print(f"TILING={c:.1f}: mean weight {w:.4f}")
