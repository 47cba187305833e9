"""``comgs demo``: the whole pipeline on embedded, procedural inputs (no download).

1. inputs: a procedural object (torus + ball), a sunny procedural sky for the scene and a
   dim blue studio map for the object capture (``data.procedural``);
2. ground truth path-traced by Mitsuba (``make-dataset composition``): the scene capture
   (gravel ground, brick wall, box, SfM points), the object alone under the studio map, and
   the real composites of the object standing on the ground under the sky;
3. the object reconstructed (step 1 + step 2: materials, env map, SOPs) and the scene
   reconstructed (step 1);
4. the lighting estimated at the placement from the reconstructed scene (360-degree trace,
   completion network, EV-bracket fusion), occlusion cached in shadow probes;
5. the composition rendered with SOP shadows, with traced shadows and as a naive paste, each
   scored against the path-traced composites;
6. ``report.html``: one self-contained page (``comgs_dr.eval.report``).

Every stage writes its (time, metric) records to its folder's ``metrics.jsonl``.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from comgs_dr import set_variant
from comgs_dr.core import colorspace, runlog
from comgs_dr.data import placement_probe, procedural
from comgs_dr.data.composition_dataset import CompositionDatasetConfig, make_composition_dataset
from comgs_dr.data.images import read_image, to_u8
from comgs_dr.data.load import load_dataset
from comgs_dr.eval import comp_region, lighting_metrics, report
from comgs_dr.lighting import backends, envmap
from comgs_dr.stages.compose import PRESETS as COMPOSE_PRESETS
from comgs_dr.stages.compose import compose
from comgs_dr.stages.decompose import MaterialConfig, train_material
from comgs_dr.stages.estimate_light import EstimateConfig, estimate_light, write_outputs
from comgs_dr.stages.reconstruct import RadianceConfig, train_radiance
from comgs_dr.stages.render_comp import render_comp
from comgs_dr.train.run import write_run_info

OBJECT = "torus"
OBJECT_MATERIAL = {"texture": None, "base_color": (0.8, 0.35, 0.1), "roughness": 0.35,
                   "metallic": 0.0}
VARIANTS = ("sop", "trace", "paste")
OBJECT_LIGHTS = ("learnt", "known")


@dataclasses.dataclass
class DemoConfig:
    """Sizes of the demo. Presets (``PRESETS``): ``default`` (128 px captures, 256 px
    composites: about 11 minutes on 2 CPU cores) and ``tiny`` (a smoke test for tests and
    CI, about a minute; its numbers mean nothing).

    Sizes in pixels, angles in degrees. The scene is captured from ``scene_views`` views
    looking down at the ground (``scene_elevation_deg``) and ``sky_views`` from eye height
    over the horizon (``sky_pitch_deg``), which see the sky and the sun (default none: real
    captures rarely look at the sun, so the light comes from the scene's shadows and the
    ground, ``estimate_light``; 12 gives the capture that saw it); the object from
    ``object_views``; ``test_views`` composites are scored. ``spp``: samples per pixel of the
    path-traced ground truth; ``rays``: S_r of the composition renders (step 2 uses at most
    64). ``object_light``: ``learnt`` (step 2 learns the object's capture light, the general
    case) or ``known`` (step 2 under the object's studio map, ``decompose --env-file``).
    ``probe_height``: rows of the true light path-traced at the placement, the reference of
    the lighting error. Example: ``run_demo(dataclasses.replace(PRESETS["tiny"],
    out_dir="out/t"))``.
    """
    out_dir: str = "out/demo"
    resolution: int = 128                       # the captures (scene, object)
    comp_resolution: int | None = 256           # the composition frames (None: resolution)
    scene_views: int = 40
    object_views: int = 36
    test_views: int = 4
    spp: int = 32
    sfm_points: int = 5000
    scene_elevation_deg: tuple = (30.0, 70.0)   # views looking down at the ground
    sky_views: int = 0                          # capture views over the horizon (sky and sun):
                                                # 0, as most real captures (the sun from the
                                                # shadows, the sky's level from the ground); 12:
                                                # the second case, a capture that saw the sun
    sky_pitch_deg: tuple = (10.0, 40.0)
    scene_env_resolution: int = 128             # texels per side of step 1's sky
    sun_elevation_deg: float = 25.0
    sun_radius_deg: float = 3.0                 # the sky's sun disc (its power is fixed)
    scene_exposure: float = 0.6                 # exposed for the sky: only the sun clips
    scene_background: str = "env"               # step 1 learns the sky behind the surfels
    scene_iterations: int = 800
    object_iterations: int = 800
    material_iterations: int = 300
    object_light: str = "learnt"                # learnt | known (see above)
    probes: int = 2000
    shadow_probes: int = 2000
    rays: int = 128
    probe_height: int = 256                     # rows of the true light at the placement
    seed: int = 0
    progress: bool = True

    def __post_init__(self):
        """Sizes are checked here, before anything is written or rendered."""
        if self.object_light not in OBJECT_LIGHTS:
            raise ValueError(f"DemoConfig.object_light must be learnt or known, got "
                             f"{self.object_light!r}")
        lows = {"resolution": 8, "sfm_points": 0, "seed": 0, "sky_views": 0, "probe_height": 4}
        if self.comp_resolution is not None and (isinstance(self.comp_resolution, bool) or not
                                                 isinstance(self.comp_resolution, int)
                                                 or self.comp_resolution < 8):
            raise ValueError(f"DemoConfig.comp_resolution must be None or an integer >= 8, "
                             f"got {self.comp_resolution!r}")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.type in (int, "int") and (isinstance(v, bool) or not isinstance(v, int)
                                           or v < lows.get(f.name, 1)):
                raise ValueError(f"DemoConfig.{f.name} must be an integer >= "
                                 f"{lows.get(f.name, 1)}, got {v!r}")


PRESETS = {
    "default": DemoConfig(),
    "tiny": DemoConfig(resolution=24, comp_resolution=32, scene_views=8, sky_views=2, object_views=8, test_views=2,
                       spp=4,
                       sfm_points=800, scene_iterations=30, object_iterations=30,
                       material_iterations=10, probes=200, shadow_probes=150, rays=16,
                       probe_height=32),
}


def _stage(name: str, times: dict, progress: bool):
    """Context manager timing one stage into ``times`` (and announcing it)."""
    class _T:
        def __enter__(self):
            if progress:
                print(f"[demo] {name} ...", flush=True)
            self.t = time.perf_counter()

        def __exit__(self, *exc):
            times[name] = round(time.perf_counter() - self.t, 2)
            if progress and exc[0] is None:
                print(f"[demo] {name}: {times[name]:.1f} s", flush=True)
    return _T()


def comparison_figure(comp_gt: Path, renders: dict, names: list[str], scores: dict) -> Image.Image:
    """Rows = test frames, columns = ground truth | each variant, with per-frame PSNR."""
    cols = [("ground truth", comp_gt, None)] + [(v, p, scores[v]) for v, p in renders.items()]
    tiles = [[read_image(d / f"{n}.png")[..., :3] for _, d, _ in cols] for n in names]
    h, w = tiles[0][0].shape[:2]
    s = max(1, 192 // w)
    bar = 14
    sheet = Image.new("RGB", (len(cols) * (w * s + 4), len(names) * (h * s + bar)), "white")
    draw = ImageDraw.Draw(sheet)
    for r, row in enumerate(tiles):
        for c, img in enumerate(row):
            x, y = c * (w * s + 4), r * (h * s + bar)
            sheet.paste(Image.fromarray(to_u8(img)).resize((w * s, h * s), Image.NEAREST),
                        (x, y + bar))
            label, _, sc = cols[c]
            if sc is not None:
                label += f"  {sc['per_frame'][r]['psnr']:.2f} dB"
            draw.text((x + 2, y + 1), label, fill=(0, 0, 0))
    return sheet


def region_figures(comp_data: Path, renders: dict, names: list[str], out: Path) -> None:
    """``crops.png`` (the shadow and the object at full size: truth | each variant) and
    ``shadow_profile.png`` (darkness along the shadow's axis) of the frame whose truth has
    the most shadow pixels (``eval.comp_region``)."""
    from comgs_dr.core.exr import read_image as read_exr
    best = None
    for n in names:
        gt = read_image(comp_data / "gt" / f"{n}.png")[..., :3]
        empty = read_exr(comp_data / "empty" / f"{n}.exr")[..., :3]
        obj = read_image(comp_data / "mask" / f"{n}.png")
        obj = (obj[..., 0] if obj.ndim == 3 else obj) > 0.5
        shadow = comp_region.regions(colorspace.srgb_decode(gt), empty, obj)[0]
        if best is None or shadow.sum() > best[0].sum():
            best = (shadow, obj, gt, empty, n)
    shadow, obj, gt, empty, n = best
    preds = {v: read_image(d / f"{n}.png")[..., :3] for v, d in renders.items()}
    comp_region.crops_figure(gt, preds, obj, shadow).save(out / "crops.png")
    png = comp_region.profile_png(gt, empty, preds, shadow)
    if png is not None:
        (out / "shadow_profile.png").write_bytes(png)


def envmap_figure(true_eq: np.ndarray, est_eq: np.ndarray, width: int = 384) -> Image.Image:
    """True | estimated equirect maps at the placement (same exposure, ``colorspace.tonemap``)."""
    scale = 1.0 / max(float(np.percentile(true_eq @ colorspace.LUMA, 90)), 1e-6)
    panels = []
    for label, m in (("true light at the placement", true_eq),
                     ("estimated at the placement", est_eq)):
        x = np.clip(m * scale * 0.5, 0, None)
        img = Image.fromarray(to_u8(colorspace.tonemap(x))).resize(
            (width, width // 2), Image.BILINEAR)
        canvas = Image.new("RGB", (width, width // 2 + 14), "white")
        canvas.paste(img, (0, 14))
        ImageDraw.Draw(canvas).text((2, 1), label, fill=(0, 0, 0))
        panels.append(canvas)
    sheet = Image.new("RGB", (2 * width + 4, panels[0].height), "white")
    sheet.paste(panels[0], (0, 0))
    sheet.paste(panels[1], (width + 4, 0))
    return sheet


def run_demo(cfg: DemoConfig) -> dict:
    """Run the demo into ``cfg.out_dir``; returns the summary written to ``demo.json``."""
    variant = set_variant("auto")
    t_start = time.perf_counter()
    out = Path(cfg.out_dir)
    (out / "inputs").mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}
    prog = cfg.progress
    with _stage("inputs + path-traced ground truth", times, prog):
        ds, studio = _ground_truth(cfg, out)
        meta = json.loads((ds / "composition.json").read_text())
    scene_run, obj_run = out / "scene_run", out / "object_run"
    with _stage("scene step 1 (surfels)", times, prog):
        s1 = _scene_step1(cfg, ds, scene_run)
    with _stage("object step 1 (surfels)", times, prog):
        o1 = _object_step1(cfg, ds, obj_run)
    with _stage("object step 2 (materials, env map, SOPs)", times, prog):
        o2 = _object_step2(cfg, obj_run, studio)
    estimator = PlacementEstimator(str(scene_run / "point_cloud.ply"), backends.default_backend())
    comp = out / "comp"
    with _stage("lighting estimation + occlusion caching", times, prog):
        edit = _compose(cfg, ds, scene_run, obj_run, comp, estimator)
        write_outputs(estimator.estimate, out / "light" / "estimate.exr")
    with _stage("rendering the composition", times, prog):
        scores = _render_composition(cfg, ds, comp)
    names = [f["name"] for f in scores["sop"]["per_frame"]]
    light = _figures_and_light_error(cfg, out, ds, comp, scores, names, estimator, meta)
    summary = {
        "variant": variant, "config": dataclasses.asdict(cfg), "stage_seconds": times,
        "total_seconds": round(time.perf_counter() - t_start, 1),
        **_composition_scores(scores, names),
        "scene_step1_psnr_test": s1["psnr_test"], "object_step1_psnr_test": o1["psnr_test"],
        "object_step2_psnr_test": o2["psnr_test"], **light,
        "edit_seconds": edit["timings"],
    }
    (out / "demo.json").write_text(json.dumps(runlog.json_safe(summary), indent=1,
                                              allow_nan=False))
    runlog.rewrite(out, runlog.part_records("demo", times))
    report.write_report(out, out / "report.html", title="comgs demo")
    summary["report"] = str(out / "report.html")
    return summary


class PlacementEstimator:
    """``compose``'s estimator: the lighting at a placement estimated from the reconstructed
    scene (``estimate_light``, outdoor label); keeps the last position and estimate."""

    def __init__(self, scene_ply: str, backend):
        self.scene_ply, self.backend = scene_ply, backend
        self.position: np.ndarray | None = None
        self.estimate: dict | None = None

    def __call__(self, pos, name) -> np.ndarray:
        self.position = np.asarray(pos, np.float64)
        self.estimate = estimate_light(self.scene_ply, pos, EstimateConfig(label="outdoor"),
                                       self.backend)
        return self.estimate["hdr"]


def _ground_truth(cfg: DemoConfig, out: Path) -> tuple[Path, Path]:
    """The procedural inputs in ``inputs/`` and the path-traced composition dataset in
    ``dataset/``; returns (the dataset folder, the studio map)."""
    mesh = procedural.procedural_object_yup(out / "inputs" / f"{OBJECT}.ply")
    sky = procedural.procedural_sky(out / "inputs" / "sky.exr",
                                    sun_elevation_deg=cfg.sun_elevation_deg,
                                    sun_radius_deg=cfg.sun_radius_deg)
    studio = procedural.procedural_studio(out / "inputs" / "studio.exr")
    ds = out / "dataset"
    make_composition_dataset(CompositionDatasetConfig(
        out_dir=ds, objects=(str(mesh),), scene_map=sky, object_map=studio,
        resolution=cfg.resolution, comp_resolution=cfg.comp_resolution,
        scene_views=cfg.scene_views,
        object_views=cfg.object_views, test_views=cfg.test_views, spp=cfg.spp,
        sfm_points=cfg.sfm_points, seed=cfg.seed, path_material=OBJECT_MATERIAL,
        scene_elevation_deg=cfg.scene_elevation_deg, sky_views=cfg.sky_views,
        sky_pitch_deg=cfg.sky_pitch_deg,
        scene_envmap_scale=cfg.scene_exposure),
        progress=cfg.progress)
    return ds, studio


def _scene_step1(cfg: DemoConfig, ds: Path, scene_run: Path) -> dict:
    write_run_info(scene_run, ds / "scene", "scene", 1, False)
    return train_radiance(load_dataset(ds / "scene"), scene_run, RadianceConfig.from_preset(
        "scene", iterations=cfg.scene_iterations, eval_every=max(cfg.scene_iterations // 8, 1),
        eval_views=4, seed=cfg.seed, background=cfg.scene_background,
        env_resolution=cfg.scene_env_resolution), progress=cfg.progress)


def _object_step1(cfg: DemoConfig, ds: Path, obj_run: Path) -> dict:
    write_run_info(obj_run, ds / "objects" / OBJECT, "object", 1, False)
    return train_radiance(load_dataset(ds / "objects" / OBJECT), obj_run,
                          RadianceConfig.from_preset(
                              "object", iterations=cfg.object_iterations,
                              eval_every=max(cfg.object_iterations // 8, 1), eval_views=4,
                              seed=cfg.seed), progress=cfg.progress)


def _object_step2(cfg: DemoConfig, obj_run: Path, studio: Path) -> dict:
    return train_material(obj_run, None, MaterialConfig(
        iterations=cfg.material_iterations, probe_count=cfg.probes, rays=min(cfg.rays, 64),
        eval_every=max(cfg.material_iterations // 6, 1), eval_views=4,
        env_file=str(studio) if cfg.object_light == "known" else None), progress=cfg.progress)


def _compose(cfg: DemoConfig, ds: Path, scene_run: Path, obj_run: Path, comp: Path,
             estimator: PlacementEstimator) -> dict:
    """``compose`` (fast preset, ``shadow_probes`` occlusion probes) into ``comp``."""
    ccfg = COMPOSE_PRESETS["fast"]
    ccfg = dataclasses.replace(ccfg, shadow=dataclasses.replace(ccfg.shadow,
                                                                count=cfg.shadow_probes))
    return compose(scene_run, {OBJECT: obj_run}, ds / "transform.json", comp,
                   estimator=estimator, cfg=ccfg, progress=cfg.progress)


def _render_composition(cfg: DemoConfig, ds: Path, comp: Path) -> dict:
    """{variant: render_comp's scores} of every variant against the path-traced composites."""
    scores = {}
    for v in VARIANTS:
        scores[v] = render_comp(comp, ds / "comp" / "transforms_test.json", v,
                                ds / "comp" / "gt", rays=cfg.rays, seed=cfg.seed,
                                progress=cfg.progress)
    return scores


def _figures_and_light_error(cfg: DemoConfig, out: Path, ds: Path, comp: Path, scores: dict,
                             names: list, estimator: PlacementEstimator, meta: dict) -> dict:
    """comparison.png, crops.png / shadow_profile.png, envmaps.png, and the lighting error
    at the placement: against the true light arriving there (the scene without the object,
    path-traced from the placement) and against the scene's map, which ignores the scene's
    shadows and ground."""
    renders = {v: comp / "renders" / v for v in VARIANTS}
    comparison_figure(ds / "comp" / "gt", renders, names, scores).save(out / "comparison.png")
    region_figures(ds / "comp", renders, names, out)
    est = estimator.estimate["hdr"]
    true_eq = placement_probe.render_probe(placement_probe.empty_scene(ds),
                                           estimator.position, cfg.probe_height, 8)
    envmap_figure(true_eq, est).save(out / "envmaps.png")
    light_err = lighting_metrics.compare_maps(est, true_eq)
    map_eq = envmap.read_envmap_file(meta["scene"]["envmap"])[0] * meta["scene"]["envmap_scale"]
    return {"lighting": light_err, "lighting_vs_map": lighting_metrics.compare_maps(est, map_eq)}


def _composition_scores(scores: dict, names: list) -> dict:
    """The summary's composition part: each variant's PSNR/SSIM/time, its scores in the
    object's region, and on how many frames SOP beats the naive paste."""
    sop, paste = scores["sop"]["per_frame"], scores["paste"]["per_frame"]
    return {
        "composition": {v: {"psnr": scores[v]["psnr"], "ssim": scores[v]["ssim"],
                            "frame_seconds": scores[v]["frame_seconds"]} for v in VARIANTS},
        "sop_beats_paste_frames": int(sum(a["psnr"] > b["psnr"] for a, b in zip(sop, paste))),
        "frames": len(names),
        "region": {v: scores[v].get("region") for v in VARIANTS},
        "sop_beats_paste_frames_region": int(sum(
            a.get("psnr_region", -np.inf) > b.get("psnr_region", np.inf)
            for a, b in zip(sop, paste))),
    }
