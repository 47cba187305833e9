"""``comgs sfm``: poses from photos (COLMAP via pycolmap) on a rendered capture with known
cameras, the photo and video preparation, and the errors a user meets (exit 2, no traceback)."""
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image, ImageDraw, ImageFilter

from comgs_dr.cli.sfm import main as sfm_main
from comgs_dr.data import photos
from comgs_dr.stages import sfm as S

pycolmap = pytest.importorskip("pycolmap")

# ----------------------------------------------------------------------------- a capture

W, H, FOCAL = 320, 240, 280.0
SCENE_SIZE = 2.0              # the three textured planes span [0, 2]^3


def _texture(seed: int, size: int = 512) -> np.ndarray:
    """A texture rich in corners and blobs at several scales (SIFT finds plenty)."""
    rng = np.random.default_rng(seed)
    im = Image.new("RGB", (size, size), tuple(int(v) for v in rng.integers(60, 200, 3)))
    d = ImageDraw.Draw(im)
    for r in (60, 30, 14, 7):
        for _ in range(int(3000 / r)):
            x, y = rng.uniform(0, size, 2)
            box = [x - r * rng.uniform(0.3, 1), y - r * rng.uniform(0.3, 1),
                   x + r * rng.uniform(0.3, 1), y + r * rng.uniform(0.3, 1)]
            fill = tuple(int(v) for v in rng.integers(0, 256, 3))
            (d.ellipse if rng.random() < 0.5 else d.rectangle)(box, fill=fill)
    return np.asarray(im.filter(ImageFilter.GaussianBlur(0.7)), np.float32)


def _look_at(eye, target) -> np.ndarray:
    """OpenCV camera-to-world [3, 3] (+X right, +Y down, +Z forward), world up +Z."""
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    return np.stack([r, np.cross(f, r), f], 1)


def _render(eye, rot, textures, ss: int = 2) -> np.ndarray:
    """Ray-cast the floor z=0 and the walls x=0, y=0 (each [0, 2]^2, textured)."""
    u, v = np.meshgrid((np.arange(W * ss) + 0.5) / ss, (np.arange(H * ss) + 0.5) / ss)
    d = np.stack([(u - W / 2) / FOCAL, (v - H / 2) / FOCAL, np.ones_like(u)], -1) @ rot.T
    best, colour = np.full(u.shape, np.inf), np.full(u.shape + (3,), 128.0, np.float32)
    for axis, tex in zip((2, 0, 1), textures):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -eye[axis] / d[..., axis]
        p = eye + t[..., None] * d
        uv = np.delete(p, axis, -1) / SCENE_SIZE                     # [h, w, 2] in [0, 1]
        hit = (t > 0) & (t < best) & np.all((uv >= 0) & (uv <= 1), -1)
        n = tex.shape[0] - 1
        ij = np.clip(uv * n, 0, n)
        i0 = np.floor(ij).astype(int).clip(0, n - 1)
        f = ij - i0
        c = sum(tex[i0[..., 1] + dy, i0[..., 0] + dx] * (((1 - f[..., 0]) if dx == 0 else f[..., 0]) *
                                                          ((1 - f[..., 1]) if dy == 0 else f[..., 1]))[..., None]
                for dx in (0, 1) for dy in (0, 1))
        colour[hit], best[hit] = c[hit], t[hit]
    img = colour.reshape(H, ss, W, ss, 3).mean((1, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def _cameras(n: int = 12) -> list:
    target = np.array([0.6, 0.6, 0.5])
    out = []
    for k, az in enumerate(np.radians(np.linspace(20, 70, n))):
        eye = np.array([3.2 * np.cos(az), 3.2 * np.sin(az), 1.5 + 0.25 * np.sin(k)])
        out.append((eye, _look_at(eye, target)))
    return out


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """12 rendered photos + one corrupt file, and the true camera centres by name."""
    root = tmp_path_factory.mktemp("capture")
    textures = [_texture(s) for s in (1, 2, 3)]
    centres = {}
    for i, (eye, rot) in enumerate(_cameras()):
        name = f"view_{i:02d}.jpg"
        Image.fromarray(_render(eye, rot, textures)).save(root / name, quality=95)
        centres[name] = eye
    (root / "broken.jpg").write_bytes(b"\xff\xd8 not a jpeg at all")
    return root, centres


@pytest.fixture(scope="module")
def solved(capture, tmp_path_factory):
    root, centres = capture
    out = tmp_path_factory.mktemp("sfm") / "data"
    lines = []
    cfg = S.SfmConfig(threads=2, max_size=0)
    report = S.run_sfm(root, out, cfg, progress=False, say=lines.append)
    return out, report, centres


def umeyama(src: np.ndarray, dst: np.ndarray):
    """Similarity (s, R, t) minimising |s R src + t - dst|^2 (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, sig, vt = np.linalg.svd(cov)
    e = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2, 2] = -1
    r = u @ e @ vt
    s = np.trace(np.diag(sig) @ e) / xs.var(0).sum()
    return s, r, mu_d - s * r @ mu_s


# ----------------------------------------------------------------------------- the stage

def test_registers_every_photo_with_small_error(solved):
    out, r, _ = solved
    assert (r["registered"], r["given"]) == (12, 12)
    assert r["unreadable"] == ["broken.jpg"] and "broken.jpg" in r["warnings"][0]
    assert r["mean_reprojection_error_px"] < 1.0
    assert r["points"] > 300 and r["matching"] == "exhaustive" and r["camera_mode"] == "single"
    assert set(r["seconds"]) >= {"prepare", "extract", "match", "map", "undistort", "total"}
    assert json.loads((out / "sfm.json").read_text())["registered"] == 12


def test_camera_centres_match_the_true_ones_up_to_a_similarity(solved):
    out, _, centres = solved
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    names = sorted(centres)
    got = {rec.image(i).name: np.asarray(rec.image(i).projection_center()) for i in rec.reg_image_ids()}
    src = np.array([got[n] for n in names])
    dst = np.array([centres[n] for n in names])
    s, rot, t = umeyama(src, dst)
    err = np.linalg.norm((s * src @ rot.T + t) - dst, axis=1)
    assert err.max() < 0.03 * SCENE_SIZE, err


def test_output_is_a_colmap_folder_the_package_loads(solved):
    from comgs_dr.data.load import load_dataset
    out, _, _ = solved
    cams = pycolmap.Reconstruction(str(out / "sparse" / "0")).cameras
    assert {c.model.name for c in cams.values()} == {"PINHOLE"}
    data = load_dataset(out, pixels=False)
    assert len(data.train) + len(data.test) == 12 and len(data.test) == 2
    cam = data.train[0].camera
    assert abs(cam.width - W) <= 8 and abs(cam.height - H) <= 8
    fov = 2 * np.degrees(np.arctan(W / (2 * FOCAL)))
    assert abs(cam.fov_x_deg - fov) < 0.05 * fov, (cam.fov_x_deg, fov)


def test_sequential_pairs_are_linear_plus_quadratic(solved):
    out, _, _ = solved
    run = SimpleNamespace(cfg=S.SfmConfig(sequential_overlap=2))
    with pycolmap.Database.open(str(out / "distorted" / "database.db")) as db:
        ids = sorted(im.image_id for im in db.read_all_images())
        pairs = S._pairs(run, pycolmap, "sequential", db)
        assert len(S._pairs(run, pycolmap, "exhaustive", db)) == 66
    step = {ids.index(b) - ids.index(a) for a, b in pairs}
    assert len(pairs) == 11 + 10 + 8 + 4 and step == {1, 2, 4, 8}       # 12 images


def test_unposed_captures_are_recognised(solved, capture, tmp_path):
    out, _, _ = solved
    root, _ = capture
    assert S.is_unposed_capture(root) and not S.is_unposed_capture(out)   # out: a COLMAP folder
    (tmp_path / "cap" / "images").mkdir(parents=True)
    Image.new("RGB", (8, 8)).save(tmp_path / "cap" / "images" / "a.png")
    (tmp_path / "cap" / "LICENSE").write_text("MIT")
    assert S.is_unposed_capture(tmp_path / "cap") and not S.is_unposed_capture(tmp_path / "nope")
    assert S.photo_folder(tmp_path / "cap") == tmp_path / "cap" / "images"


# ----------------------------------------------------------------------------- preparation

def test_exif_orientation_is_applied_and_the_long_side_limited(tmp_path):
    im = Image.fromarray(np.tile(np.arange(200, dtype=np.uint8)[None, :, None], (100, 1, 3)))
    exif = Image.Exif()
    exif[0x0112] = 6                                  # stored landscape, shown rotated 90° CW
    exif[0x0110] = "Phone"
    im.save(tmp_path / "a.jpg", exif=exif.tobytes(), quality=95)
    p = photos.prepare_photo(tmp_path / "a.jpg", tmp_path / "b.jpg", max_size=80)
    assert (p.width, p.height, p.source_size, p.rotated, p.resized) == (40, 80, (200, 100), True, True)
    with Image.open(tmp_path / "b.jpg") as out:
        assert out.size == (40, 80)
        assert 0x0112 not in out.getexif() and out.getexif()[0x0110] == "Phone"
        a = np.asarray(out.convert("L"), np.float32)
    assert a[5, 20] < a[-5, 20]                       # column gradient became a row gradient
    p = photos.prepare_photo(tmp_path / "a.jpg", tmp_path / "c.jpg", max_size=0)
    assert (p.width, p.height, p.rotated, p.resized) == (100, 200, True, False)
    Image.new("RGB", (30, 20), (10, 20, 30)).save(tmp_path / "u.jpg", quality=90)
    photos.prepare_photo(tmp_path / "u.jpg", tmp_path / "v.jpg", max_size=1600)
    assert (tmp_path / "v.jpg").read_bytes() == (tmp_path / "u.jpg").read_bytes()   # copied
    Image.fromarray(np.full((8, 8), 40000, np.uint16)).save(tmp_path / "g16.png")
    photos.prepare_photo(tmp_path / "g16.png", tmp_path / "g8.png", max_size=0)
    assert abs(int(np.asarray(Image.open(tmp_path / "g8.png"))[0, 0, 0]) - 40000 // 257) <= 1


def test_sharpness_and_frame_choice():
    rng = np.random.default_rng(0)
    sharp = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
    blurred = np.asarray(Image.fromarray(sharp).filter(ImageFilter.GaussianBlur(3)))
    assert photos.sharpness(sharp) > 10 * photos.sharpness(blurred)
    assert photos.sharpest_per_group([1, 5, 2, 9, 3, 4, 7], 3) == [1, 3, 6]
    assert photos.blurry([10, 11, 2, 12, 9], 0.3) == [2]
    info = {"duration": 10.0, "fps": 30.0}
    assert photos.sample_rate(info, 2.0, 0, 3) == 6.0
    assert photos.sample_rate(info, 2.0, 40, 3) == 12.0
    assert photos.sample_rate(info, 20.0, 0, 3) == 30.0          # never above the video


def test_video_is_sampled_to_the_sharpest_frames(tmp_path, capture):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    root, _ = capture
    frames = [np.asarray(Image.open(p)) for p in sorted(root.glob("view_*.jpg"))[:6]]
    seq = []
    for f in frames:                        # per photo: blurred, sharp, blurred at 6 fps
        soft = np.asarray(Image.fromarray(f).filter(ImageFilter.GaussianBlur(4)))
        seq += [soft, f, soft]
    video = tmp_path / "clip.mp4"
    w = imageio_ffmpeg.write_frames(str(video), (W, H), fps=6, quality=9, macro_block_size=16)
    w.send(None)
    for f in seq:
        w.send(np.ascontiguousarray(f))
    w.close()
    run = S._Run(video, tmp_path / "out", S.SfmConfig(fps=2.0, blur_group=3), False, lambda s: None)
    S.prepare_images(run)
    v = run.report["video"]
    assert v["candidates"] == 18 and run.report["given"] == v["kept"] == 6
    kept = sorted((run.work / "images").glob("frame_*.jpg"))
    assert len(kept) == 6 and Image.open(kept[0]).size == (W, H)
    s = [photos.sharpness(np.asarray(Image.open(k))) for k in kept]
    soft = photos.sharpness(np.asarray(Image.fromarray(frames[0]).filter(ImageFilter.GaussianBlur(4))))
    assert min(s) > 3 * soft                  # the sharp frame of each group was kept


def test_disconnected_models_name_the_images_that_fell_out():
    def model(names):
        ims = {i: SimpleNamespace(name=n) for i, n in enumerate(names)}
        return SimpleNamespace(num_reg_images=lambda: len(ims), reg_image_ids=lambda: list(ims),
                               image=lambda i: ims[i])
    given = [f"{c}.jpg" for c in "abcdefgh"]
    models = {0: model(given[2:4]), 1: model(given[:2] + given[4:7])}
    warned = []
    run = SimpleNamespace(report={"prepared": [{"name": n} for n in given]}, source=Path("P"),
                          cfg=S.SfmConfig(min_registered=0.5), warn=warned.append)
    best = S.keep_largest(run, models)
    assert best is models[1] and run.report["dropped_images"] == ["c.jpg", "d.jpg", "h.jpg"]
    assert "2 disconnected models (5, 2 images)" in warned[0] and "c.jpg, d.jpg, h.jpg" in warned[0]
    run.cfg = S.SfmConfig(min_registered=0.7)
    with pytest.raises(S.SfmError, match="fell out: c.jpg, d.jpg, h.jpg"):
        S.keep_largest(run, models)


# ----------------------------------------------------------------------------- errors, exit 2

def _photos(folder: Path, n: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        Image.new("RGB", (64, 48), (i * 40, 90, 200)).save(folder / f"p{i}.png")
    return folder


@pytest.mark.parametrize("setup, message", [
    (lambda d: _photos(d / "two", 2), "2 image(s); structure from motion needs at least 3"),
    (lambda d: (d / "empty").mkdir() or d / "empty", "no images"),
    (lambda d: d / "missing", "no such folder or video file"),
])
def test_bad_input_exits_2_with_the_problem(tmp_path, capsys, setup, message):
    src = setup(tmp_path)
    assert sfm_main([str(src), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("comgs sfm: error: ") and message in err and "Traceback" not in err
    assert str(src) in err


def test_unreadable_files_are_named(tmp_path, capsys):
    src = _photos(tmp_path / "p", 2)
    (src / "bad.jpg").write_bytes(b"garbage")
    (src / "worse.png").write_bytes(b"")
    assert sfm_main([str(src), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "2 unreadable image(s)" in err and "bad.jpg" in err and "worse.png" in err


def test_bad_flags_and_foreign_out_folder_exit_2(tmp_path, capsys):
    src = _photos(tmp_path / "p", 3)
    out = tmp_path / "o"
    assert sfm_main([str(src), "--out", str(out), "--matching", "vocab"]) == 2
    assert sfm_main([str(src), "--out", str(out), "--max-size", "10"]) == 2
    assert "max_size must be 0 or >= 64" in capsys.readouterr().err
    assert sfm_main([str(src), "--out", str(out), "--fps", "nan"]) == 2
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert sfm_main([str(src), "--out", str(out)]) == 2
    assert "is not an earlier `comgs sfm` output" in capsys.readouterr().err
    assert not (out / "images").exists()
    inside = _photos(tmp_path / "o2" / "images", 3)          # the photos where DATA/images goes
    assert sfm_main([str(inside), "--out", str(tmp_path / "o2")]) == 2
    assert "may not be in" in capsys.readouterr().err


def test_unmatchable_photos_say_so(tmp_path, capsys):
    src = _photos(tmp_path / "flat", 3)                 # flat colours: no features
    assert sfm_main([str(src), "--out", str(tmp_path / "out"), "--quiet", "--threads", "1"]) == 2
    err = capsys.readouterr().err
    assert "share enough matching features" in err or "no image could be registered" in err


def test_flags_come_from_the_config():
    import argparse

    from comgs_dr.cli.sfm import _add_sfm
    from comgs_dr.core.config import config_overrides
    p = argparse.ArgumentParser()
    _add_sfm(p.add_subparsers(dest="command"))
    args = p.parse_args(["sfm", "P", "--out", "D", "--max-size", "800", "--frames", "40",
                         "--matching", "sequential", "--keep-work", "false"])
    assert config_overrides(args, S.SfmConfig) == dict(max_size=800, frames=40,
                                                        matching="sequential", keep_work=False)
    assert config_overrides(p.parse_args(["sfm", "P", "--out", "D"]), S.SfmConfig) == {}
