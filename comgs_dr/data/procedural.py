"""Procedural inputs shipped as code (no download): objects, a table-top scene and HDR maps.

Used by ``comgs demo`` (the whole pipeline on embedded inputs), ``comgs make-dataset scene``,
the notebooks and the tests. Meshes are written as PLY, maps as equirect EXR in the package's
Z-up orientation (u = 0.5 - atan2(y, x)/2pi, v = acos(z)/pi, Blender's convention).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from comgs_dr.data.synthetic import ObjectDatasetConfig
from comgs_dr.lighting.envmap import write_exr


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


def procedural_sky(path: Path, width: int = 256, sun_elevation_deg: float = 40.1,
                   sun_azimuth_deg: float = 45.8, sun_radius_deg: float = 3.0) -> Path:
    """Equirect HDR sky (Z-up, the dataset's orientation): gradient, ground, a bright sun at
    the given elevation / azimuth (from +X towards +Y). Its power does not depend on
    ``sun_radius_deg`` (radiance 400 at 3 degrees, scaled by (3 / radius)²); the real sun's
    radius is 0.27 degrees, below what a 256-px map resolves."""
    d = _directions(width)
    up = np.clip(d[..., 2], 0, 1)[..., None]
    sky = (1 - up) * np.array([0.9, 0.95, 1.1]) + up * np.array([0.25, 0.45, 1.0])
    ground = np.array([0.25, 0.2, 0.15])
    img = np.where(d[..., 2:3] > 0, sky, ground)
    el, az = np.radians(sun_elevation_deg), np.radians(sun_azimuth_deg)
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    rad = 400.0 * (1 - np.cos(np.radians(3.0))) / (1 - np.cos(np.radians(sun_radius_deg)))
    img = img + rad * (d @ sun > np.cos(np.radians(sun_radius_deg)))[..., None] \
        * np.array([1.0, 0.95, 0.85])
    return write_exr(path, img.astype(np.float32), "equirect")


def _directions(width: int) -> np.ndarray:
    """[H, W, 3] world directions of the equirect texel centres (H = width / 2)."""
    h = width // 2
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(width) + 0.5) / width, indexing="ij")
    theta, phi = v * np.pi, (0.5 - u) * 2 * np.pi
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def procedural_studio(path: Path, width: int = 256) -> Path:
    """Equirect HDR 'studio' (Z-up): a dim blue-grey room with one large soft key light
    (a 25-degree cap at 45 degrees elevation) and a dark floor. Objects captured under it look
    nothing like they do under :func:`procedural_sky`, so pasting them unchanged is visibly
    wrong (the case composition is for)."""
    d = _directions(width)
    img = np.where(d[..., 2:3] > 0, np.array([0.16, 0.18, 0.24]), np.array([0.06, 0.06, 0.07]))
    key = np.array([np.cos(0.78) * np.cos(-2.2), np.cos(0.78) * np.sin(-2.2), np.sin(0.78)])
    cap = d @ key > np.cos(np.radians(25.0))
    img = img + 4.0 * cap[..., None] * np.array([0.85, 0.9, 1.0])
    return write_exr(path, img.astype(np.float32), "equirect")


def procedural_object_yup(path: Path) -> Path:
    """:func:`procedural_object` turned Y-up (the convention of object captures)."""
    tmp = Path(path).with_suffix(".zup.ply")
    mesh = trimesh.load(procedural_object(tmp), force="mesh")
    tmp.unlink()
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    mesh.export(path)
    return Path(path)
