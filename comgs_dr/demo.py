"""``comgs demo``: the foundation end to end on embedded, procedural inputs (no download).

1. a procedural object (torus + sphere, Z-up PLY) and a procedural HDR sky with a sun;
2. a small SynCom-style dataset path-traced by Mitsuba (:mod:`comgs_dr.data.synthetic`);
3. surfels sampled on the object (:func:`comgs_dr.surfels.from_mesh`), saved as PLY;
4. G-buffers of a test view compared with the path-traced ground truth (normal, depth);
5. a short differentiable fit of the surfel colours (SH) to the training views with
   ``mi.ad.Adam`` through ``surfel_gbuffer``, test PSNR before and after;
6. a contact sheet PNG and a JSON summary.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import trimesh
from PIL import Image, ImageDraw
from tqdm import tqdm

from comgs_dr import set_variant
from comgs_dr.core import cameras
from comgs_dr.data.images import to_u8
from comgs_dr.data.synthetic import ObjectDatasetConfig, make_object_dataset
from comgs_dr.surfels import from_mesh, save_ply
from comgs_dr.surfels.scene import gbuffer_scene


@dataclasses.dataclass
class DemoConfig:
    out_dir: str = "out/demo"
    resolution: int = 64
    n_train: int = 24
    n_test: int = 6
    spp: int = 32
    surfels: int = 20_000
    fit_iterations: int = 60
    learning_rate: float = 0.05
    seed: int = 0
    progress: bool = True


def procedural_object(path: Path) -> Path:
    """A torus with a sphere through its hole, as a Z-up PLY."""
    torus = trimesh.creation.torus(major_radius=0.65, minor_radius=0.22, major_sections=96,
                                   minor_sections=32)
    torus.apply_transform(trimesh.transformations.rotation_matrix(0.5, [1, 0, 0]))
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.35)
    mesh = trimesh.util.concatenate([torus, ball])
    mesh.export(path)
    return path


def procedural_scene(path: Path) -> Path:
    """A small Z-up scene as PLY: a ground slab with a torus, a ball, a box and a pillar on it."""
    T = trimesh.transformations
    parts = [
        trimesh.creation.box((3.0, 3.0, 0.1), transform=T.translation_matrix([0, 0, -0.05])),
        trimesh.creation.torus(major_radius=0.35, minor_radius=0.12, major_sections=64, minor_sections=24),
        trimesh.creation.icosphere(subdivisions=3, radius=0.3),
        trimesh.creation.box((0.5, 0.4, 0.6)),
        trimesh.creation.cylinder(radius=0.12, height=1.0, sections=32),
    ]
    parts[1].apply_translation([-0.6, 0.5, 0.12])
    parts[2].apply_translation([0.6, 0.4, 0.3])
    parts[3].apply_transform(T.concatenate_matrices(T.translation_matrix([0.2, -0.7, 0.3]),
                                                    T.rotation_matrix(0.6, [0, 0, 1])))
    parts[4].apply_translation([-0.8, -0.6, 0.5])
    # Flat-faced parts get their own vertices per face: Mitsuba averages vertex normals of a PLY
    # without normals, and averaged normals at box corners made ~5 % of the object's pixels
    # render pure black (shading normal facing away from the camera) in the ground truth.
    for i in (0, 3, 4):
        parts[i].unmerge_vertices()
    trimesh.util.concatenate(parts).export(path)
    return path


def scene_dataset_config(out_dir, n_train: int = 60, n_test: int = 12, resolution: int = 96,
                         points: int = 20_000, seed: int = 0, spp: int = 32):
    """``ObjectDatasetConfig`` of the procedural table-top scene (``procedural_scene`` under
    ``procedural_sky``, written into ``out_dir``) with an SfM-like ``points3d.ply`` of
    ``points`` points (0: none): the scene preset's test case, ``comgs make-dataset scene``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return ObjectDatasetConfig(
        mesh=procedural_scene(out / "scene_mesh.ply"), envmap=procedural_sky(out / "scene_sky.exr"),
        out_dir=out, n_train=n_train, n_test=n_test, resolution=resolution, spp=spp, spp_aov=4,
        relight_envmaps=(), up_axis="z", texture=None, base_color=(0.55, 0.5, 0.45),
        train_elevation_deg=(15.0, 75.0), sfm_points=points, seed=seed)


def procedural_sky(path: Path, width: int = 256) -> Path:
    """Equirect HDR sky (Z-up, the dataset's orientation): gradient, ground, small bright sun."""
    h = width // 2
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(width) + 0.5) / width, indexing="ij")
    theta, phi = v * np.pi, (0.5 - u) * 2 * np.pi
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    up = np.clip(d[..., 2], 0, 1)[..., None]
    sky = (1 - up) * np.array([0.9, 0.95, 1.1]) + up * np.array([0.25, 0.45, 1.0])
    ground = np.array([0.25, 0.2, 0.15])
    img = np.where(d[..., 2:3] > 0, sky, ground)
    sun = np.array([np.cos(0.7) * np.cos(0.8), np.cos(0.7) * np.sin(0.8), np.sin(0.7)])
    img = img + 400.0 * (d @ sun > np.cos(np.radians(3.0)))[..., None] * np.array([1.0, 0.95, 0.85])
    mi.Bitmap(img.astype(np.float32), pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(path))
    return path


def run_demo(cfg: DemoConfig) -> dict:
    """Run the demo; returns the summary written to ``<out>/summary.json``."""
    variant = set_variant("auto")


    t_start = time.perf_counter()
    out = Path(cfg.out_dir)
    (out / "inputs").mkdir(parents=True, exist_ok=True)
    mesh_path = procedural_object(out / "inputs" / "object.ply")
    sky_path = procedural_sky(out / "inputs" / "sky.exr")

    # 1-2. path-traced dataset
    ds_dir = out / "dataset"
    ds = make_object_dataset(ObjectDatasetConfig(
        mesh=mesh_path, envmap=sky_path, out_dir=ds_dir, n_train=cfg.n_train, n_test=cfg.n_test,
        resolution=cfg.resolution, spp=cfg.spp, spp_aov=8, relight_envmaps=(), up_axis="z",
        texture=None, base_color=(0.7, 0.45, 0.3), seed=cfg.seed), progress=cfg.progress)
    meta = json.loads((ds_dir / "meta.json").read_text())

    # 3. surfels on the normalised object
    tm = trimesh.load(mesh_path, force="mesh")
    tm.apply_transform(np.asarray(meta["object"]["object_to_world"]))
    params = from_mesh(tm, cfg.surfels, seed=cfg.seed)
    save_ply(params, str(out / "object_surfels.ply"))

    def frames(split):
        d = json.loads((ds_dir / f"transforms_{split}.json").read_text())
        fov = np.degrees(d["camera_angle_x"])
        sensors = [cameras.from_matrix(f["to_world_mitsuba"], fov, cfg.resolution) for f in d["frames"]]
        imgs = [np.asarray(Image.open(ds_dir / (f["file_path"] + ".png")), np.float32) / 255 for f in d["frames"]]
        return d["frames"], sensors, imgs

    train_frames, train_sensors, train_imgs = frames("train")
    test_frames, test_sensors, test_imgs = frames("test")
    scene = gbuffer_scene({"obj": params}, train_sensors + test_sensors, max_hits=32)
    integ = scene.integrator()
    n_tr = len(train_sensors)

    def target(img):          # RGBA (straight alpha) -> colour over black, the G-buffer's colour
        return img[..., :3] * img[..., 3:4]

    def test_psnr():
        vals = []
        for i in range(len(test_sensors)):
            c = np.array(integ.split(mi.render(scene, sensor=n_tr + i))["color"])
            mse = np.mean((np.clip(c, 0, 1) - target(test_imgs[i])) ** 2)
            vals.append(10 * np.log10(1.0 / max(mse, 1e-12)))
        return float(np.mean(vals))

    # 4. geometry vs path-traced ground truth (test view 0)
    bufs = {k: np.array(v) for k, v in integ.split(mi.render(scene, sensor=n_tr)).items()}
    gt_n = np.array(mi.Bitmap(str(ds_dir / test_frames[0]["normal_path"])))[..., :3]
    gt_d = np.array(mi.Bitmap(str(ds_dir / test_frames[0]["depth_path"])))
    gt_d = gt_d[..., 0] if gt_d.ndim == 3 else gt_d
    mask = (test_imgs[0][..., 3] > 0.99) & (bufs["weight"][..., 0] > 0.9)
    n_hat = bufs["normal"] / np.maximum(np.linalg.norm(bufs["normal"], axis=-1, keepdims=True), 1e-8)
    cosang = np.clip(np.sum(n_hat * gt_n / np.maximum(np.linalg.norm(gt_n, axis=-1, keepdims=True), 1e-8), -1), -1, 1)
    normal_mae = float(np.degrees(np.arccos(cosang[mask])).mean())
    depth_rel = float(np.median(np.abs(bufs["depth_unbiased"][..., 0][mask] - gt_d[mask]) / gt_d[mask]))

    # 5. differentiable colour fit
    psnr0 = test_psnr()
    mp = mi.traverse(scene)
    opt = mi.ad.Adam(lr=cfg.learning_rate)
    opt["obj.sh"] = mp["obj.sh"]
    mp.update(opt)
    rng = np.random.default_rng(cfg.seed)
    targets = [mi.TensorXf(target(im).astype(np.float32)) for im in train_imgs]
    t_fit = time.perf_counter()
    it = range(cfg.fit_iterations)
    if cfg.progress:
        it = tqdm(it, desc="fit surfel colours", unit="it")
    for _ in it:
        i = int(rng.integers(n_tr))
        img = mi.render(scene, mp, sensor=i, seed=int(rng.integers(1 << 30)))
        loss = dr.mean(dr.abs(img[:, :, 0:3] - targets[i]), axis=None)
        dr.backward(loss)
        opt.step()
        mp.update(opt)
    t_fit = time.perf_counter() - t_fit
    psnr1 = test_psnr()
    save_ply(params, str(out / "object_surfels_fitted.ply"))

    # 6. contact sheet: GT | colour | weight | depth | normal | albedo (test view 0)
    bufs = {k: np.array(v) for k, v in integ.split(mi.render(scene, sensor=n_tr)).items()}
    sheet = contact_sheet([
        ("path-traced GT", target(test_imgs[0])),
        ("surfel colour (fitted)", bufs["color"]),
        ("weight W", bufs["weight"]),
        ("depth D/W", bufs["depth_unbiased"] / max(bufs["depth_unbiased"].max(), 1e-6)),
        ("normal N", 0.5 * bufs["normal"] + 0.5 * bufs["weight"]),
        ("albedo A", bufs["albedo"]),
    ])
    sheet.save(out / "gbuffers.png")
    summary = {
        "variant": variant, "resolution": cfg.resolution, "surfels": params.count,
        "dataset_seconds": ds["seconds"], "normal_mae_deg_vs_gt": normal_mae,
        "depth_median_rel_error_vs_gt": depth_rel, "test_psnr_before_fit": psnr0,
        "test_psnr_after_fit": psnr1, "fit_iterations": cfg.fit_iterations,
        "fit_seconds": t_fit, "total_seconds": time.perf_counter() - t_start,
        "outputs": {"dataset": str(ds_dir), "surfels": str(out / "object_surfels_fitted.ply"),
                    "figure": str(out / "gbuffers.png")},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def contact_sheet(panels, scale: int = 3):
    """PIL image of labelled panels ([H, W, 1|3] float arrays, linear → sRGB-ish display)."""
    tiles = []
    for label, a in panels:
        a = np.asarray(a, np.float32)
        a = np.repeat(a, 3, -1) if a.shape[-1] == 1 else a[..., :3]
        im = Image.fromarray(to_u8(a)).resize(
            (a.shape[1] * scale, a.shape[0] * scale), Image.NEAREST)
        canvas = Image.new("RGB", (im.width, im.height + 14), (255, 255, 255))
        canvas.paste(im, (0, 14))
        ImageDraw.Draw(canvas).text((2, 1), label, fill=(0, 0, 0))
        tiles.append(canvas)
    sheet = Image.new("RGB", (sum(t.width for t in tiles) + 4 * (len(tiles) - 1), tiles[0].height),
                      (255, 255, 255))
    x = 0
    for t in tiles:
        sheet.paste(t, (x, 0))
        x += t.width + 4
    return sheet
