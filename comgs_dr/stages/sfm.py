"""``comgs sfm``: camera poses and sparse points from a folder of photos or a video (COLMAP).

Phases, each one function and one progress line with its counts and seconds:

1. **prepare**: photos turned upright by their EXIF orientation, the long side limited to
   ``max_size``, unreadable files named and skipped; a video sampled to frames with ffmpeg,
   the sharpest of every ``blur_group`` candidates kept and the blurriest dropped
   (``data.photos``). The copies land in ``DATA/distorted/images``.
2. **extract**: SIFT features (pycolmap), one camera for the capture when every image has the
   same size and EXIF camera, else one per image.
3. **match**: exhaustive matching up to ``exhaustive_max`` images, sequential (each image with
   its ``sequential_overlap`` successors by name, plus quadratic steps) for video frames and
   larger sets; both with geometric verification. Pairs come from pycolmap's pair generators
   and are matched in chunks so a bar can show the progress.
4. **map**: COLMAP's incremental mapper; every model it builds is kept in ``distorted/sparse``.
5. **undistort**: the largest model's images resampled to PINHOLE cameras, written as
   ``DATA/images`` + ``DATA/sparse/0`` (the layout ``data.load.load_dataset`` reads).
6. **report**: ``DATA/sfm.json``: registered / given images, mean reprojection error (px),
   points, track length, cameras, the images that fell out, seconds per phase.

Errors a user can fix raise :class:`SfmError` (a ValueError naming the file and the
problem; the CLI exits 2): fewer than 3 images, unreadable files when fewer than 3 others
remain, no matched pairs, nothing registered, a largest model holding fewer than
``min_registered`` of the images (several disconnected models).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm.auto import tqdm

from comgs_dr.core.runlog import json_safe
from comgs_dr.data import photos
from comgs_dr.data.images import IMAGE_EXTENSIONS
from comgs_dr.data.load import load_dataset
from comgs_dr.data.types import DatasetError

MATCHING = ("auto", "exhaustive", "sequential")
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "SIMPLE_PINHOLE")
CAMERA_MODES = ("auto", "single", "per_image")
MIN_IMAGES = 3
WORK = "distorted"                 # DATA/distorted: prepared images, database, raw models
REPORT = "sfm.json"


class SfmError(DatasetError):
    """Structure from motion cannot go on with this input (the message says why and names
    the files)."""


@dataclass
class SfmConfig:
    """Settings of ``comgs sfm`` (:func:`run_sfm`).

    max_size: longest image side in pixels given to SIFT and written to ``DATA/images``
        (default 1600; 0 keeps the size). Phone photos of 4000 px gain little pose accuracy
        above it and cost ~(size/1600)^2 more time.
    matching: ``auto`` (default: exhaustive up to ``exhaustive_max`` photos, sequential for a
        video or a larger folder), ``exhaustive`` (every pair) or ``sequential`` (each image
        with its successors by file name: capture order for phone and camera names).
    exhaustive_max: ``auto`` matches exhaustively up to this many images (default 150;
        exhaustive cost grows with the square of the count).
    sequential_overlap: successors matched per image in sequential matching (default 15),
        plus the images 2, 4, 8, ... ahead (quadratic overlap) to close gaps.
    camera_model: COLMAP model fitted before undistortion: ``SIMPLE_RADIAL`` (default: one
        focal length, principal point, one radial term: right for phone lenses),
        ``RADIAL`` (two terms: wide lenses) or ``SIMPLE_PINHOLE`` (no distortion).
    camera_mode: ``auto`` (default: one shared camera when every image has the same size
        and EXIF camera and focal length, else one per image), ``single`` or ``per_image``.
    max_features: SIFT features kept per image, the larger-scale ones first (default 4096).
        CPU matching time per pair grows about as the square of it; 4096 bounds it for
        1600-px phone photos (~5000 features) at a small loss of matches.
    fps: video frames kept per second of video (default 2.0).
    frames: video frames kept, spread evenly over the video (default 0: use ``fps``).
    blur_group: video candidates decoded per kept frame; the sharpest of each group of
        consecutive candidates is kept (default 3; 1: no choice).
    blur_min_ratio: kept video frames whose sharpness (variance of the Laplacian) is below
        this fraction of the median are dropped too (default 0.3; 0: none).
    min_registered: fraction of the given images the largest model must register, else
        SfmError listing the images that fell out (default 0.5). Above it, a warning lists
        them and the largest model is kept.
    threads: CPU threads for COLMAP (default 0: the cores this process may use).
    seed: random seed of COLMAP's RANSAC and mapper (default 0).
    keep_work: keep ``DATA/distorted`` (prepared images, ``database.db``, every raw model)
        for inspection (default True); False removes it at the end.
    colmap_log: show COLMAP's own log on stderr (default False: errors only).
    """
    max_size: int = 1600
    matching: str = "auto"
    exhaustive_max: int = 150
    sequential_overlap: int = 15
    camera_model: str = "SIMPLE_RADIAL"
    camera_mode: str = "auto"
    max_features: int = 4096
    fps: float = 2.0
    frames: int = 0
    blur_group: int = 3
    blur_min_ratio: float = 0.3
    min_registered: float = 0.5
    threads: int = 0
    seed: int = 0
    keep_work: bool = True
    colmap_log: bool = False

    def __post_init__(self):
        for name, allowed in (("matching", MATCHING), ("camera_model", CAMERA_MODELS),
                              ("camera_mode", CAMERA_MODES)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"SfmConfig.{name} must be one of {', '.join(allowed)}, "
                                 f"got {getattr(self, name)!r}")
        for name, low in (("max_size", 0), ("exhaustive_max", 0), ("sequential_overlap", 1),
                          ("max_features", 64), ("frames", 0), ("blur_group", 1),
                          ("threads", 0)):
            if getattr(self, name) < low:
                raise ValueError(f"SfmConfig.{name} must be >= {low}, got {getattr(self, name)}")
        if 0 < self.max_size < 64:
            raise ValueError(f"SfmConfig.max_size must be 0 or >= 64 pixels, got {self.max_size}")
        if not self.fps > 0:
            raise ValueError(f"SfmConfig.fps must be > 0, got {self.fps}")
        if not 0 <= self.blur_min_ratio < 1:
            raise ValueError("SfmConfig.blur_min_ratio must be in [0, 1), got "
                             f"{self.blur_min_ratio}")
        if not 0 <= self.min_registered <= 1:
            raise ValueError("SfmConfig.min_registered must be in [0, 1], got "
                             f"{self.min_registered}")


@dataclass
class _Run:
    """What the phases share: paths, settings, log and the report being filled."""
    source: Path
    out: Path
    cfg: SfmConfig
    progress: bool
    say: Callable[[str], None]
    threads: int = 1
    report: dict = field(default_factory=dict)

    @property
    def work(self) -> Path:
        return self.out / WORK

    @property
    def images(self) -> Path:
        return self.work / "images"

    @property
    def database(self) -> Path:
        return self.work / "database.db"

    def warn(self, msg: str) -> None:
        print(f"sfm: warning: {msg}", file=sys.stderr, flush=True)
        self.report.setdefault("warnings", []).append(msg)

    def phase(self, name: str, t0: float, text: str) -> None:
        dt = time.perf_counter() - t0
        self.report.setdefault("seconds", {})[name] = round(dt, 2)
        self.say(f"sfm: {name:<9} {text} in {dt:.1f} s")


def run_sfm(source, out, cfg: SfmConfig | None = None, progress: bool = True,
            say: Callable[[str], None] | None = None) -> dict:
    """Poses and points of the photos in folder ``source`` (or the video file ``source``)
    into the COLMAP folder ``out`` (``images/``, ``sparse/0/``, ``sfm.json``); returns the
    report (also written to ``out/sfm.json``). ``say``: where the phase lines go (default
    print; silent when ``progress`` is False). Raises SfmError (see the module docstring)."""
    cfg = cfg or SfmConfig()
    say = say or ((lambda s: print(s, flush=True)) if progress else (lambda s: None))
    run = _Run(Path(source), Path(out), cfg, progress, say, threads=cpu_threads(cfg.threads))
    check_paths(run)
    import pycolmap  # heavy: loaded only when SfM runs
    run.report.update(source=str(run.source), out=str(run.out), pycolmap=pycolmap.__version__,
                      threads=run.threads, config=asdict(cfg),
                      source_fingerprint=source_fingerprint(run.source))
    t_all = time.perf_counter()
    with colmap_quiet(pycolmap, not cfg.colmap_log):
        pycolmap.set_random_seed(cfg.seed)
        prepare_images(run)
        extract_features(run, pycolmap)
        match_features(run, pycolmap)
        models = map_images(run, pycolmap)
        best = keep_largest(run, models)
        undistort(run, pycolmap, best)
    return write_report(run, best, t_all)


# ----------------------------------------------------------------------------- reuse

#: SfmConfig fields that do not change the result (an earlier output is reused across them)
RESULT_NEUTRAL = ("threads", "keep_work", "colmap_log")


def source_fingerprint(source) -> str:
    """A digest of the input: name, size and modification time of every photo of the folder
    (or of the video file); a changed, added or removed photo changes it."""
    p = Path(source)
    files = [p] if p.is_file() else photos.list_images(p)[0]
    parts = [(f.name, f.stat().st_size, f.stat().st_mtime_ns) for f in files]
    return hashlib.sha1(json.dumps(parts).encode()).hexdigest()[:16]


def reusable_output(source, out, cfg: SfmConfig | None = None) -> tuple[dict | None, str]:
    """(the report of ``out``, "") when ``out`` is a complete ``comgs sfm`` output of this
    ``source`` with this ``cfg`` (``RESULT_NEUTRAL`` fields aside), else (None, why not)."""
    cfg, out, src = cfg or SfmConfig(), Path(out), Path(source)
    path = out / REPORT
    if not path.is_file():
        return None, f"no {REPORT} in {out}"
    try:
        r = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        return None, f"{path} is unreadable ({e})"
    if not isinstance(r, dict) or not (out / "images").is_dir() or \
            not (out / "sparse" / "0").is_dir() or "registered" not in r:
        return None, f"{out} holds an incomplete SfM output"
    if src.is_dir():
        try:
            src = photo_folder(src)
        except SfmError as e:
            return None, str(e)
    if r.get("source_fingerprint") != source_fingerprint(src):
        return None, f"the photos in {src} differ from those {out} was made from"
    old = {k: v for k, v in (r.get("config") or {}).items() if k not in RESULT_NEUTRAL}
    new = {k: v for k, v in asdict(cfg).items() if k not in RESULT_NEUTRAL}
    if old != new:
        diff = ", ".join(f"{k} {old.get(k)!r} -> {v!r}" for k, v in new.items()
                         if old.get(k) != v)
        return None, f"the settings differ from {out}'s ({diff})"
    return r, ""


def ensure_sfm(source, out, cfg: SfmConfig | None = None, progress: bool = True,
               say: Callable[[str], None] | None = None) -> tuple[dict, bool]:
    """(report, reused): ``out``'s report when it is a complete output of this ``source``
    and ``cfg`` (:func:`reusable_output`), else :func:`run_sfm` into ``out`` (an earlier
    output there is replaced). What lets ``comgs reconstruct PHOTOS`` be run again."""
    say = say or ((lambda s: print(s, flush=True)) if progress else (lambda s: None))
    report, why = reusable_output(source, out, cfg)
    if report is not None:
        return report, True
    if Path(out, REPORT).is_file() or Path(out, WORK).is_dir():
        say(f"sfm: redoing {out}: {why}")
    return run_sfm(source, out, cfg, progress=progress, say=say), False


# ----------------------------------------------------------------------------- setup

def cpu_threads(requested: int = 0) -> int:
    """``requested`` threads, or (0) the cores this process may run on."""
    if requested > 0:
        return requested
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:                      # not Linux
        return max(1, os.cpu_count() or 1)


def check_paths(run: _Run) -> None:
    """The source exists; ``out`` is new, empty or an earlier ``comgs sfm`` output (whose
    products are replaced) and does not hold the source."""
    src, out = run.source, run.out
    if not src.exists():
        raise SfmError(f"{src}: no such folder or video file")
    if src.is_file() and not photos.is_video(src):
        raise SfmError(f"{src}: not a folder of photos nor a video "
                       f"({', '.join(photos.VIDEO_EXTENSIONS)})")
    if out.exists() and not out.is_dir():
        raise SfmError(f"{out}: exists and is not a folder")
    if src.is_dir():
        run.source = src = photo_folder(src)
    for product in (out / "images", out / WORK, out / "sparse"):
        if _inside(src, product):
            raise SfmError(f"{src}: the photos may not be in {product}, which `comgs sfm` "
                           f"writes; move them elsewhere (e.g. {out / 'input'})")
    if out.is_dir() and any(out.iterdir()) and not _is_sfm_output(out):
        raise SfmError(f"{out}: exists, is not empty and is not an earlier `comgs sfm` output; "
                       "choose a new --out folder")


def photo_folder(folder: Path) -> Path:
    """``folder``, or the one subfolder holding its photos when it holds none itself (a
    capture folder ``plush/images/*.jpg`` beside a LICENSE); ``images`` or ``input`` win
    when several subfolders hold images."""
    if photos.list_images(folder)[0]:
        return folder
    subs = [d for d in sorted(folder.iterdir()) if d.is_dir() and not d.name.startswith(".")
            and photos.list_images(d)[0]]
    named = [d for d in subs if d.name in ("images", "input")]
    if len(subs) == 1 or len(named) == 1:
        return (named or subs)[0]
    if subs:
        raise SfmError(f"{folder}: no images here but in {len(subs)} subfolders "
                       f"({', '.join(d.name for d in subs[:6])}); give the one to use")
    return folder


def is_unposed_capture(path) -> bool:
    """True for a video file, or a folder (or its one photo subfolder) of images that is no
    dataset ``data.load`` reads (no transforms json, COLMAP model or poses_bounds.npy): what
    ``comgs sfm`` is for. Lets a command that takes a dataset run SfM first."""
    from comgs_dr.data.load import detect_format
    p = Path(path)
    if photos.is_video(p):
        return True
    if not p.is_dir():
        return False
    try:
        detect_format(p)
        return False
    except DatasetError:
        pass
    try:
        return bool(photos.list_images(photo_folder(p))[0])
    except SfmError:
        return False


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def _is_sfm_output(out: Path) -> bool:
    return (out / REPORT).is_file() or (out / WORK).is_dir()


@contextlib.contextmanager
def colmap_quiet(pycolmap, quiet: bool):
    """COLMAP's log limited to errors while the block runs (``quiet``)."""
    old = pycolmap.logging.minloglevel
    if quiet:
        pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _bar(run: _Run, total: int, desc: str, unit: str):
    return tqdm(total=total, desc=f"sfm: {desc}", unit=unit, disable=not run.progress,
                leave=False, dynamic_ncols=True)


# ----------------------------------------------------------------------------- 1. prepare

def prepare_images(run: _Run) -> None:
    """Upright, size-limited copies of the photos (or video frames) in ``work/images``."""
    t0 = time.perf_counter()
    files = _list_photos(run) if run.source.is_dir() else None
    _clear_products(run)
    items = _prepare_photos(run, files) if files is not None else _prepare_video(run)
    kind = "photos" if files is not None else "video"
    run.report.update(kind=kind, given=len(items), prepared=[asdict(p) for p in items])
    if len(items) < MIN_IMAGES:
        raise SfmError(f"{run.source}: {len(items)} usable image(s); structure from motion "
                       f"needs at least {MIN_IMAGES} overlapping views")
    w, h = items[0].width, items[0].height
    run.phase("prepare", t0, f"{len(items)} images ({w}x{h} first; "
              f"{sum(p.rotated for p in items)} turned upright, "
              f"{sum(p.resized for p in items)} downsized"
              + (f" to <= {run.cfg.max_size} px)" if run.cfg.max_size else ")"))


def _clear_products(run: _Run) -> None:
    """Remove an earlier run's products (check_paths made sure ``out`` is ours or new)."""
    for d in (run.out / "images", run.out / "sparse", run.work):
        shutil.rmtree(d, ignore_errors=True)
    (run.out / REPORT).unlink(missing_ok=True)
    run.images.mkdir(parents=True)


def _list_photos(run: _Run) -> list:
    files, other = photos.list_images(run.source)
    if not files:
        extra = f" (it holds {len(other)} other file(s), e.g. {other[0].name})" if other else ""
        raise SfmError(f"{run.source}: no images ({', '.join(IMAGE_EXTENSIONS)}){extra}")
    if len(files) < MIN_IMAGES:
        raise SfmError(f"{run.source}: {len(files)} image(s); structure from motion needs at "
                       f"least {MIN_IMAGES} overlapping views")
    return files


def _prepare_photos(run: _Run, files: list) -> list:
    items, bad = [], []
    for f in tqdm(files, desc="sfm: prepare", unit="image", disable=not run.progress,
                  leave=False, dynamic_ncols=True):
        dst = run.images / _output_name(f)
        try:
            items.append(photos.prepare_photo(f, dst, run.cfg.max_size))
        except ValueError as e:
            bad.append((f.name, str(e)))
    _handle_unreadable(run, bad, len(items))
    return items


def _output_name(f: Path) -> str:
    """The prepared copy's name: the photo's own for JPEG/PNG, else the name + .png
    (``a.tif.png``: unique beside an ``a.png``)."""
    return f.name if f.suffix.lower() in (".jpg", ".jpeg", ".png") else f.name + ".png"


def _handle_unreadable(run: _Run, bad: list, good: int) -> None:
    run.report["unreadable"] = [n for n, _ in bad]
    if not bad:
        return
    detail = "; ".join(msg for _, msg in bad[:5])
    detail += f"; and {len(bad) - 5} more" if len(bad) > 5 else ""
    if good < MIN_IMAGES:
        raise SfmError(f"{len(bad)} unreadable image(s) in {run.source}, {good} readable "
                       f"(at least {MIN_IMAGES} needed): {detail}")
    run.warn(f"skipped {len(bad)} unreadable image(s): {detail}")


def _prepare_video(run: _Run) -> list:
    """The sharpest frame of every ``blur_group`` candidates, less the blurry ones."""
    cfg = run.cfg
    try:
        info = photos.video_info(run.source)
    except ImportError as e:
        raise ImportError("videos need imageio-ffmpeg (pip install imageio-ffmpeg)") from e
    except (OSError, RuntimeError, StopIteration, IndexError, ValueError) as e:
        raise SfmError(f"{run.source}: unreadable video ({e})") from None
    rate = photos.sample_rate(info, cfg.fps, cfg.frames, cfg.blur_group)
    kept, candidates = _sample_sharpest(run, rate, info)
    drop = set(photos.blurry([p.sharpness for p in kept], cfg.blur_min_ratio))
    for i in drop:
        (run.images / kept[i].name).unlink()
    items = [p for i, p in enumerate(kept) if i not in drop]
    run.report["video"] = dict(info, rate=rate, candidates=candidates, kept=len(items),
                               dropped_blurry=len(drop))
    run.say(f"sfm: video     {candidates} candidate frames at {rate:.2f}/s over "
            f"{info['duration']:.1f} s; kept the sharpest of every {cfg.blur_group}: "
            f"{len(kept)}; dropped {len(drop)} blurry (< {cfg.blur_min_ratio} x median "
            f"sharpness): {len(items)} frames")
    return items


def _sample_sharpest(run: _Run, rate: float, info: dict) -> tuple[list, int]:
    """(PreparedImage of the sharpest of each run of ``blur_group`` candidates decoded at
    ``rate``, written at once so that only one group is held in memory; candidate count)."""
    group, kept, buf, n = run.cfg.blur_group, [], [], 0
    total = int(round(rate * info["duration"]))
    bar = _bar(run, total or None, "decode", "frame")
    try:
        for frame in photos.read_video_frames(run.source, rate):
            buf.append((photos.sharpness(frame), n / rate, frame))
            n += 1
            bar.update()
            if len(buf) == group:
                kept.append(_save_frame(run, *max(buf, key=lambda b: b[0]), len(kept), total))
                buf.clear()
    except (OSError, RuntimeError) as e:
        raise SfmError(f"{run.source}: video decoding failed after {n} frames ({e})") from None
    finally:
        bar.close()
    if buf:
        kept.append(_save_frame(run, *max(buf, key=lambda b: b[0]), len(kept), total))
    return kept, n


def _save_frame(run: _Run, score: float, seconds: float, frame: np.ndarray, index: int,
                total: int):
    """Write one kept frame (``seconds`` into the video) as ``frame_<index>.jpg``."""
    from PIL import Image
    im = Image.fromarray(frame)
    size = photos.fit_size(*im.size, run.cfg.max_size)
    resized = size != im.size
    if resized:
        im = im.resize(size, Image.LANCZOS)
    name = photos.frame_name(index, total)
    photos.save_image(im, run.images / name)
    return photos.PreparedImage(name, f"{run.source}@{seconds:.2f}s", im.width, im.height,
                                (frame.shape[1], frame.shape[0]), False, resized, round(score, 2))


# ----------------------------------------------------------------------------- 2. extract

def camera_mode(run: _Run, pycolmap):
    """pycolmap.CameraMode: single for a video or a uniform capture (``auto``)."""
    mode = run.cfg.camera_mode
    if mode == "auto":
        mode = "single" if run.report["kind"] == "video" or _uniform(run) else "per_image"
    run.report["camera_mode"] = mode
    return pycolmap.CameraMode.SINGLE if mode == "single" else pycolmap.CameraMode.PER_IMAGE


def _uniform(run: _Run) -> bool:
    """Every prepared image has one size and one EXIF (make, model, focal length)."""
    from PIL import Image
    keys = set()
    for p in run.report["prepared"]:
        with Image.open(run.images / p["name"]) as im:
            ex = im.getexif()
            sub = ex.get_ifd(0x8769)
            keys.add((im.size, ex.get(0x010F), ex.get(0x0110), sub.get(0x920A), sub.get(0xA405)))
        if len(keys) > 1:
            return False
    return True


def extract_features(run: _Run, pycolmap) -> None:
    """SIFT keypoints and descriptors of every prepared image into the database."""
    t0 = time.perf_counter()
    names = [p["name"] for p in run.report["prepared"]]
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = run.cfg.camera_model
    mode = camera_mode(run, pycolmap)
    pycolmap.Database.open(str(run.database)).close()             # an empty database
    pycolmap.import_images(str(run.database), str(run.images), mode, names, reader)
    opts = _extraction_options(run, pycolmap)
    step = max(1, min(16, len(names) // 20 or 1))
    with _bar(run, len(names), "extract", "image") as bar:
        for i in range(0, len(names), step):
            pycolmap.extract_features(str(run.database), str(run.images), names[i:i + step],
                                      mode, reader, opts, pycolmap.Device.cpu)
            bar.update(len(names[i:i + step]))
    with pycolmap.Database.open(str(run.database)) as db:
        kp = [db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()]
        run.report.update(cameras=db.num_cameras(), keypoints_mean=round(float(np.mean(kp)), 1))
    run.phase("extract", t0, f"{len(names)} images, {run.report['keypoints_mean']:.0f} SIFT "
              f"features per image, {run.report['cameras']} camera(s) "
              f"({run.report['camera_mode']})")


def _extraction_options(run: _Run, pycolmap):
    """SIFT for phone photos: the upsampled first octave finds the small features of a
    downsized photo; no affine shape or domain-size pooling (several times slower on a CPU
    for little gain on photos taken a few degrees apart)."""
    o = pycolmap.FeatureExtractionOptions()
    o.num_threads = run.threads
    o.use_gpu = False
    if run.cfg.max_size > 0:
        o.max_image_size = run.cfg.max_size
    o.sift.max_num_features = run.cfg.max_features
    o.sift.first_octave = -1
    o.sift.estimate_affine_shape = False
    o.sift.domain_size_pooling = False
    return o


# ----------------------------------------------------------------------------- 3. match

def matching_method(run: _Run) -> str:
    m = run.cfg.matching
    if m == "auto":
        many = run.report["given"] > run.cfg.exhaustive_max
        m = "sequential" if run.report["kind"] == "video" or many else "exhaustive"
    run.report["matching"] = m
    return m


def match_features(run: _Run, pycolmap) -> None:
    """Match the pairs of the chosen method in chunks (a bar over pairs), verify them."""
    t0 = time.perf_counter()
    method = matching_method(run)
    with pycolmap.Database.open(str(run.database)) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pairs = _pairs(run, pycolmap, method, db)
    mopts, vopts = _matching_options(run, pycolmap)
    chunk = max(64, min(1000, len(pairs) // 20 + 1))
    with _bar(run, len(pairs), f"match ({method})", "pair") as bar, \
            tempfile.TemporaryDirectory(dir=run.work) as tmp:
        for i in range(0, len(pairs), chunk):
            part = pairs[i:i + chunk]
            path = Path(tmp) / "pairs.txt"
            path.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in part))
            popts = pycolmap.ImportedPairingOptions()
            popts.match_list_path = str(path)
            pycolmap.match_image_pairs(str(run.database), mopts, popts, vopts, pycolmap.Device.cpu)
            bar.update(len(part))
    _count_verified(run, pycolmap, len(pairs))
    run.phase("match", t0, f"{method}: {len(pairs)} pairs, {run.report['verified_pairs']} "
              "verified")


def _unique(pairs) -> list:
    """Each unordered pair once (the exhaustive generator lists pairs across blocks twice)."""
    seen, out = set(), []
    for a, b in pairs:
        key = (min(a, b), max(a, b))
        if a != b and key not in seen:
            seen.add(key)
            out.append(key)
    return out


def _pairs(run: _Run, pycolmap, method: str, db) -> list:
    """Image id pairs of ``method`` from pycolmap's pair generators: every pair, or each
    image with its ``sequential_overlap`` successors by name plus those 2, 4, 8, ... ahead
    (COLMAP's quadratic overlap replaces the linear one, so both are asked for)."""
    if method == "exhaustive":
        return _unique(pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(),
                                                        db).all_pairs())
    pairs = []
    for quadratic in (False, True):
        o = pycolmap.SequentialPairingOptions()
        o.overlap = run.cfg.sequential_overlap if not quadratic else 31
        o.quadratic_overlap = quadratic
        o.loop_detection = False                 # needs a vocabulary tree file
        pairs += pycolmap.SequentialPairGenerator(o, db).all_pairs()
    return _unique(pairs)


def _matching_options(run: _Run, pycolmap):
    m = pycolmap.FeatureMatchingOptions()
    m.num_threads = run.threads
    m.use_gpu = False
    v = pycolmap.TwoViewGeometryOptions()
    v.ransac.random_seed = run.cfg.seed
    return m, v


def _count_verified(run: _Run, pycolmap, n_pairs: int) -> None:
    with pycolmap.Database.open(str(run.database)) as db:
        _, geometries = db.read_two_view_geometries()
    verified = sum(len(g.inlier_matches) > 0 for g in geometries)
    run.report.update(pairs=n_pairs, verified_pairs=int(verified))
    if verified == 0:
        raise SfmError(f"{run.source}: no two of the {run.report['given']} images share enough "
                       "matching features (0 verified pairs): the photos must overlap, be "
                       "sharp and show textured surfaces")


# ----------------------------------------------------------------------------- 4. map

def map_images(run: _Run, pycolmap) -> dict:
    """COLMAP incremental mapping: {model index: Reconstruction}, written to work/sparse."""
    t0 = time.perf_counter()
    sparse = run.work / "sparse"
    sparse.mkdir(exist_ok=True)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = run.threads
    opts.random_seed = run.cfg.seed
    opts.multiple_models = True                  # disconnected parts: report, keep the largest
    opts.ba_refine_principal_point = False
    with _bar(run, run.report["given"], "map", "image") as bar:
        models = pycolmap.incremental_mapping(
            str(run.database), str(run.images), str(sparse), opts,
            initial_image_pair_callback=lambda: bar.update(2),
            next_image_callback=lambda: bar.update(1))
    if not models:
        raise SfmError(f"{run.source}: no image could be registered "
                       f"({run.report['verified_pairs']} verified pairs among {run.report['given']} images, no pair good enough "
                       "to start a model): the photos need more overlap, sharpness or parallax")
    sizes = sorted((m.num_reg_images() for m in models.values()), reverse=True)
    run.phase("map", t0, f"{len(models)} model(s) of {', '.join(map(str, sizes))} images")
    return models


def keep_largest(run: _Run, models: dict):
    """The model with most registered images; names the images that fell out of it and
    raises SfmError when it holds fewer than ``min_registered`` of the given images."""
    ordered = sorted(models.items(), key=lambda kv: -kv[1].num_reg_images())
    idx, best = ordered[0]
    given = [p["name"] for p in run.report["prepared"]]
    inside = {best.image(i).name for i in best.reg_image_ids()}
    others = {best_i: {m.image(i).name for i in m.reg_image_ids()} for best_i, m in ordered[1:]}
    out = [n for n in given if n not in inside]
    in_other = sorted(n for names in others.values() for n in names if n not in inside)
    run.report.update(models=[m.num_reg_images() for _, m in ordered], kept_model=int(idx),
                      registered=len(inside), dropped_images=out,
                      in_other_models=in_other)
    if out:
        msg = _dropped_message(run, ordered, out, in_other, len(given))
        if len(inside) < run.cfg.min_registered * len(given):
            raise SfmError(msg + f"; fewer than {run.cfg.min_registered:.0%} of the images "
                           "registered (--min-registered)")
        run.warn(msg)
    return best


def _dropped_message(run: _Run, ordered, out: list, in_other: list, n: int) -> str:
    shown = ", ".join(out[:12]) + (f", ... ({len(out) - 12} more)" if len(out) > 12 else "")
    kept = ordered[0][1].num_reg_images()
    if len(ordered) == 1:
        return (f"{run.source}: {kept} of {n} images registered; not registered (too little "
                f"overlap, sharpness or texture): {shown}")
    sizes = ", ".join(str(m.num_reg_images()) for _, m in ordered)
    return (f"{run.source}: {len(ordered)} disconnected models ({sizes} images); kept the "
            f"largest, {kept} of {n} images; fell out: {shown} ({len(in_other)} of them in "
            "the smaller models: photos bridging the parts would join them)")


# ----------------------------------------------------------------------------- 5. undistort

def undistort(run: _Run, pycolmap, model) -> None:
    """``out/images`` + ``out/sparse/0``: the model's images resampled to PINHOLE cameras."""
    t0 = time.perf_counter()
    src = run.work / "sparse" / str(run.report["kept_model"])   # written by the mapper
    if not (src / "cameras.bin").is_file():
        src.mkdir(parents=True, exist_ok=True)
        model.write(str(src))
    opts = pycolmap.UndistortCameraOptions()
    if run.cfg.max_size > 0:
        opts.max_image_size = run.cfg.max_size
    with tempfile.TemporaryDirectory(dir=run.out, prefix=".undistort_") as tmp:
        pycolmap.undistort_images(tmp, str(src), str(run.images), output_type="COLMAP",
                                  undistort_options=opts, num_threads=run.threads)
        (run.out / "sparse").mkdir()
        os.replace(Path(tmp) / "images", run.out / "images")
        os.replace(Path(tmp) / "sparse", run.out / "sparse" / "0")
    run.phase("undistort", t0, f"{model.num_reg_images()} images to PINHOLE -> "
              f"{run.out / 'images'}, {run.out / 'sparse' / '0'}")


# ----------------------------------------------------------------------------- 6. report

def write_report(run: _Run, model, t_all: float) -> dict:
    """Fill and write ``out/sfm.json`` (``t_all``: the run's start, perf_counter); the work
    folder is removed unless ``keep_work``."""
    import pycolmap
    t0 = time.perf_counter()
    final = pycolmap.Reconstruction(str(run.out / "sparse" / "0"))
    r = run.report
    r.update(registered_fraction=round(r["registered"] / r["given"], 4),
             mean_reprojection_error_px=round(float(model.compute_mean_reprojection_error()), 4),
             points=int(model.num_points3D()),
             mean_track_length=round(float(model.compute_mean_track_length()), 3),
             mean_observations_per_image=round(
                 float(model.compute_mean_observations_per_reg_image()), 1),
             cameras_fitted=[_camera_dict(c) for c in model.cameras.values()],
             cameras_undistorted=[_camera_dict(c) for c in final.cameras.values()])
    r["loads_as"] = _check_loads(run)
    if not run.cfg.keep_work:
        shutil.rmtree(run.work, ignore_errors=True)
    r["seconds"].update(report=round(time.perf_counter() - t0, 2),
                        total=round(time.perf_counter() - t_all, 2))
    path = run.out / REPORT
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(json_safe(r), indent=1, allow_nan=False))
    os.replace(tmp, path)
    run.say(f"sfm: report    {r['registered']}/{r['given']} images registered, mean "
            f"reprojection error {r['mean_reprojection_error_px']:.3f} px, {r['points']} points, "
            f"{r['seconds']['total']:.0f} s; loads as {r['loads_as']['train']} train + "
            f"{r['loads_as']['test']} test views -> {path}")
    return r


def _check_loads(run: _Run) -> dict:
    """Load the output as ``comgs reconstruct`` will (cameras only): its split sizes."""
    try:
        data = load_dataset(run.out, pixels=False)
    except DatasetError as e:
        raise SfmError(f"{run.out}: the written model does not load ({e})") from None
    cam = data.train[0].camera
    return {"train": len(data.train), "test": len(data.test), "width": cam.width,
            "height": cam.height, "fov_x_deg": round(cam.fov_x_deg, 3)}


def _camera_dict(cam) -> dict:
    return {"model": cam.model.name, "width": int(cam.width), "height": int(cam.height),
            "params": [round(float(p), 4) for p in cam.params]}
