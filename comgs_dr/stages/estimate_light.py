"""The lighting-estimation stage: trace → complete → fuse → octahedral map (+ lights).

Paper, "Lighting Estimation" and Appendix "Details of Lighting Estimation": from the
reconstructed scene, a 360° sweep at the object's placement gives a partial RGB panorama,
a normal map and an alpha mask (``surfels.panorama.trace_panorama``); a completion model
(``lighting.backends``) generates LDR panoramas at EV {0, −2.5, −5}, which are fused into an
HDR environment map (``lighting.hdr.fuse_brackets``); lights clipped at EV 0 (a sun seen
by the capture) get their missing power back as spherical-Gaussian lobes predicted by the
light head (``lighting.lights``: the brackets alone stop at 32× the white level); the map is
converted to an octahedral texture (``lighting.envmap.equirect_to_oct_np``) for relighting and
shadows. We also extract the dominant lights (``hdr.extract_lights``).

When the scene's step-1 run learned a sky behind its surfels (``--background env``,
``train.background``), ``EstimateConfig.background`` ("auto": beside the PLY) composites it into
the trace where the surfels leave the view open and the capture saw the sky
(``panorama.composite_background``), before completion.

The scene label that conditions the completion and the light head (indoor / outdoor /
unknown) is classified from the backend's input when ``EstimateConfig.label`` is "auto" (the
default; ``lighting.scene_label``), and recorded in ``meta`` with p(outdoor).

Input of the backend: the trace's EV-0 display values ``ldr`` clipped to [0, 1] for a
radiance field fitted in sRGB (the usual case), or ``expose(rgb, 0)`` for a linear one,
with ``alpha`` as the mask and ``normal``.

Error policy:

* a bad position (not 3 finite values, outside the scene's bbox + 10 %) or an
  ``exclude_radius`` that removes every surfel: ``trace_panorama``'s ValueError, re-raised
  with the stage's context;
* **zero coverage** (nothing of the scene is seen from the position): ValueError. Completing
  an empty panorama would hallucinate an unconditioned environment that has nothing to do
  with the scene; the fills cannot run at all. Coverage below ``LOW_COVERAGE`` (the paper
  evaluates 40–100 %) only warns;
* **non-finite values** in the traced panorama (NaN/Inf from degenerate surfels): those
  pixels are treated as unobserved (alpha, colour and normal set to 0) and a warning gives
  their count; if no finite pixel is left the zero-coverage error follows.
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from comgs_dr.core.equirect import coverage, pixel_solid_angles
from comgs_dr.lighting import envmap, hdr, scene_label, sun_fit
from comgs_dr.lighting import lights as light_head
from comgs_dr.lighting.lights import TRUST_BRACKETS
from comgs_dr.lighting.backends import default_backend
from comgs_dr.lighting.completion import LABELS, CompletionBackend
from comgs_dr.stages.estimate_light_files import (  # noqa: F401  (re-exported)
    jsonable, output_paths, preview_image, write_outputs)
from comgs_dr.surfels import load_ply, panorama
from comgs_dr.surfels.panorama import PanoramaConfig
from comgs_dr.surfels.shape import SurfelShapeBase
from comgs_dr.train import background as bgenv
from comgs_dr.train.run import read_run_info

log = logging.getLogger(__name__)

__all__ = ["EstimateConfig", "LOW_COVERAGE", "check_model_files", "load_scene", "sanitize_trace",
           "backend_input", "estimate_light", "write_outputs", "output_paths", "preview_image"]

LOW_COVERAGE = 0.4      # the paper's smallest evaluated coverage (Appendix, Table supp_lgt)


@dataclass
class EstimateConfig:
    """Settings of :func:`estimate_light` (trace size, completion EVs, octahedral size).

    ``colour_space``: space of the radiance field's colour ('srgb' or 'linear'); None = the
    PLY's recorded space, or 'srgb' for a scene object. ``net_resolution`` (H, W): input size
    of the default network backend (None: ``NetworkBackend``'s default, the training size).
    """
    width: int = 1024
    height: int = 512
    max_hits: int = 32
    exclude_radius: float = 0.0
    label: str = "auto"             # "auto": classified from the trace (``lighting.
                                    # scene_label``; docs/lighting.md "The scene label"), or "outdoor",
                                    # "indoor", "unknown"
    evs: tuple = (0.0, -2.5, -5.0)
    oct_res: int = 512
    net_resolution: tuple | None = None
    supersample: int = 1
    colour_space: str | None = None
    n_lights: int = 3
    light_head: str = "default"     # weights of the light head; "default": the shipped ones
                                    # (skipped with a warning if absent); "none": no head
    scene_label: str = "default"    # the classifier of label "auto": "default" the shipped
                                    # one, or a model from ``comgs train-scene-label``
    light_head_rows: int = 256      # the head reads the panorama at most this many rows
                                    # (``head_factor``); 0: no limit
    light_trust_brackets: float = TRUST_BRACKETS  # the brackets' vote on which
                                    # clipped region holds the head's power (``add_lights``)
    background: str = "auto"        # step 1's learned sky behind the surfels: "auto" (the
                                    # PLY's run folder, if it has one), "none", or a folder
    clipped_max_texels: float = float("inf")  # the step-1 record of clipped sky
                                    # (``add_background``) is applied to its connected parts
                                    # up to this many background texels (inf: all, 0: none)
    sun_from_shadows: str = "auto"  # "auto": fit a sun to the scene's own cast shadows
                                    # (``lighting.sun_fit``) and add it where the panorama
                                    # did not observe its direction; "off"
    sun_radius_deg: float = 1.0     # angular radius of the sun added from the shadows

    def validate(self) -> None:
        if self.label not in scene_label.LABEL_CHOICES:
            raise ValueError(f"EstimateConfig.label must be one of "
                             f"{list(scene_label.LABEL_CHOICES)}, got {self.label!r}")
        if self.scene_label != "default" and self.label != "auto":
            raise ValueError(f"EstimateConfig.scene_label (a classifier) applies to label "
                             f"'auto' only; the label is {self.label!r}")
        evs = [float(e) for e in self.evs]
        if not evs or 0.0 not in evs or any(e > 0 or not np.isfinite(e) for e in evs) \
                or len(set(evs)) != len(evs):
            raise ValueError(f"EstimateConfig.evs must be distinct finite values <= 0 including "
                             f"0, got {self.evs!r}")
        if isinstance(self.oct_res, bool) or int(self.oct_res) != self.oct_res \
                or self.oct_res < 2:
            raise ValueError(f"EstimateConfig.oct_res must be an integer >= 2, got "
                             f"{self.oct_res!r}")
        if self.colour_space not in (None, "srgb", "linear"):
            raise ValueError(f"EstimateConfig.colour_space must be None, 'srgb' or 'linear', "
                             f"got {self.colour_space!r}")
        self.panorama_config("srgb").validate()          # width, height, max_hits, ...
        if self.width != 2 * self.height:                  # the map written is an equirect
            raise ValueError(f"EstimateConfig: the panorama must be 2:1 (an equirect map), got "
                             f"width {self.width} and height {self.height}")
        if isinstance(self.clipped_max_texels, bool) \
                or not float(self.clipped_max_texels) >= 0.0:
            raise ValueError(f"EstimateConfig.clipped_max_texels must be >= 0, got "
                             f"{self.clipped_max_texels!r}")
        if isinstance(self.light_head_rows, bool) \
                or int(self.light_head_rows) != self.light_head_rows or self.light_head_rows < 0:
            raise ValueError(f"EstimateConfig.light_head_rows must be an integer >= 0, got "
                             f"{self.light_head_rows!r}")
        if isinstance(self.light_trust_brackets, bool) \
                or not 0.0 <= float(self.light_trust_brackets) <= 1.0:
            raise ValueError(f"EstimateConfig.light_trust_brackets must lie in [0, 1], got "
                             f"{self.light_trust_brackets!r}")
        if isinstance(self.n_lights, bool) or int(self.n_lights) != self.n_lights \
                or self.n_lights < 0:
            raise ValueError(f"EstimateConfig.n_lights must be an integer >= 0, got "
                             f"{self.n_lights!r}")
        if self.net_resolution is not None and (
                len(self.net_resolution) != 2
                or any(isinstance(v, bool) or int(v) != v or v < 1 for v in self.net_resolution)):
            raise ValueError(f"EstimateConfig.net_resolution must be two integers >= 1 (H, W), "
                             f"got {self.net_resolution!r}")

        if self.sun_from_shadows not in ("auto", "off"):
            raise ValueError(f"EstimateConfig.sun_from_shadows must be 'auto' or 'off', got "
                             f"{self.sun_from_shadows!r}")
        if isinstance(self.sun_radius_deg, bool) or not 0.0 < float(self.sun_radius_deg) <= 10.0:
            raise ValueError(f"EstimateConfig.sun_radius_deg must be in (0, 10], got "
                             f"{self.sun_radius_deg!r}")

    def panorama_config(self, colour_space: str):
        return PanoramaConfig(width=self.width, height=self.height, max_hits=self.max_hits,
                              exclude_radius=self.exclude_radius, colour_space=colour_space,
                              supersample=self.supersample)


# ---------------------------------------------------------------------------------------
# Scene and trace handling

def load_scene(path):
    """(Mitsuba scene with one ``surfels`` shape, colour space) from a surfel PLY file.
    A Mitsuba variant must be active (``comgs_dr.set_variant``)."""

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"estimate_light: scene file not found: {p}")
    params, info = load_ply(p, return_meta=True)
    scene = mi.load_dict({"type": "scene",
                          "scene": SurfelShapeBase.from_params(params, id="scene")})
    return scene, info.color_space


def sanitize_trace(trace: dict) -> tuple[dict, int]:
    """Copy of a ``trace_panorama`` result whose non-finite pixels (any NaN/Inf in ldr, rgb,
    normal or alpha) are unobserved: alpha, colours and normal 0. Returns (trace, count)."""
    bad = ~np.isfinite(trace["alpha"])                                           # [H, W]
    for k in ("ldr", "rgb", "normal"):
        bad |= ~np.isfinite(trace[k]).all(-1)
    out = dict(trace)
    n = int(bad.sum())
    if n:
        for k in ("ldr", "rgb", "normal", "alpha", "depth"):
            if k in trace:
                out[k] = np.where(bad[..., None] if trace[k].ndim == 3 else bad, 0.0,
                                  trace[k]).astype(np.float32)
    return out, n


def backend_input(trace: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb [H,W,3] EV-0 sRGB LDR in [0, 1], normal [H,W,3], mask [H,W] in [0, 1])."""
    srgb = trace["meta"].get("colour_space", "srgb") == "srgb"
    rgb = np.clip(trace["ldr"], 0.0, 1.0) if srgb else hdr.expose(trace["rgb"], 0.0)
    return (rgb.astype(np.float32), trace["normal"].astype(np.float32),
            np.clip(trace["alpha"], 0.0, 1.0).astype(np.float32))


def _coverage(mask) -> float:
    return coverage(mask)


# ---------------------------------------------------------------------------------------
# The stage

def estimate_light(scene_or_ply_path, position, cfg: EstimateConfig | None = None,
                   backend: CompletionBackend | None = None) -> dict:
    """HDR environment map at ``position`` of a surfel scene (Mitsuba scene or PLY path).

    ``backend`` default: ``backends.default_backend(resolution=cfg.net_resolution)`` (the
    shipped net, its hole averaged with the SH fill). Returns a dict of NumPy float32 arrays and metadata:
    ``hdr`` [H, W, 3] linear equirect (trace size), ``oct`` [R, R, 3] octahedral map,
    ``ldrs`` {ev: [H, W, 3]} completions, ``input`` {"rgb", "normal", "mask"} fed to the
    backend, ``lights`` (``hdr.extract_lights``), ``coverage`` (solid-angle fraction),
    ``lobes`` (the light head's added lobes), ``light_regions`` (every clipped region the
    head read and what it did there, ``lights.describe_regions``),
    ``timings`` {load, trace, label, completion, fusion, light_head, octahedral, lights,
    total} in seconds and ``meta``.
    Errors: see the module docstring.
    """
    cfg = EstimateConfig() if cfg is None else cfg
    cfg.validate()
    check_model_files(cfg)                      # before the trace, not minutes into it
    t0 = time.perf_counter()
    timings = {}
    if isinstance(scene_or_ply_path, (str, Path)):
        scene, space = load_scene(scene_or_ply_path)
        source = str(scene_or_ply_path)
    else:
        scene, space, source = scene_or_ply_path, "srgb", "<scene>"
    space = cfg.colour_space or space
    if backend is None:
        backend = default_backend(resolution=cfg.net_resolution)
    timings["load"] = time.perf_counter() - t0

    t = time.perf_counter()
    try:
        trace = panorama.trace_panorama(scene, position, cfg.panorama_config(space))
    except ValueError as exc:
        raise ValueError(f"estimate_light: cannot trace the scene {source} at "
                         f"{np.asarray(position).tolist()}: {exc}") from exc
    timings["trace"] = time.perf_counter() - t

    trace, n_bad = sanitize_trace(trace)
    if n_bad:
        log.warning("estimate_light: %d traced pixels hold NaN/Inf (degenerate surfels?); "
                    "they are treated as unobserved", n_bad)
    bg_dir = _background_dir(cfg.background, scene_or_ply_path)
    if bg_dir is not None:
        trace = add_background(trace, bg_dir, cfg.clipped_max_texels)
    rgb, normal, mask = backend_input(trace)
    cov = _coverage(mask)
    if cov <= 0.0:
        raise ValueError(
            f"estimate_light: zero coverage at {trace['meta']['position']}: no surfel of "
            f"{source} is visible from there ({trace['meta']['surfels']} traced, "
            f"{trace['meta']['excluded']} excluded by exclude_radius={cfg.exclude_radius}). "
            f"Move the position, lower exclude_radius, or check the scene")
    if cov < LOW_COVERAGE:
        log.warning("estimate_light: coverage %.1f%% is below %.0f%% (the paper's tested "
                    "range); the completion is mostly guessed", 100 * cov, 100 * LOW_COVERAGE)

    sky_seen = hdr.seen_sky_fraction(mask)
    sky_clip = hdr.clipped_sky_fraction(rgb, mask)
    open_sky = (hdr.seen_sky_fraction(trace["background_alpha"])
                if "background_alpha" in trace else None)
    if open_sky is not None:
        log.info("estimate_light: %.1f%% of the upper hemisphere is observed, %.1f%% is open "
                 "sky (step 1's learned background), the rest surfaces", 100 * sky_seen,
                 100 * open_sky)
    if sky_seen < hdr.SEEN_SKY_WARN:
        if bg_dir is not None:
            fix = "add views that see the sky, or give the map (compose --env)"
        elif cfg.background == "none" and _background_dir("auto", scene_or_ply_path):
            fix = "the run has a learned sky that background 'none' left out: use the default " \
                  "background 'auto'"
        else:
            fix = "if the capture saw the sky, reconstruct with --background env (step 1 " \
                  "keeps no sky without it); else add sky views or give the map (compose --env)"
        log.warning("estimate_light: the capture saw %.1f%% of the upper hemisphere (sky, "
                    "ceiling, anything above the horizon) at the placement (warned below "
                    "%.0f%%): the lights up there are the completion's guess (measured through "
                    "step 1 without sky views: E(sun)/E(up) 23-81%% low, the light 40-46 deg "
                    "off), but for a sun the scene's cast shadows show (sun_from_shadows, "
                    "reported next; the demo without sky views: 3.5 deg off, the sky's power "
                    "still 0.57x); %s", 100 * sky_seen, 100 * hdr.SEEN_SKY_WARN, fix)
    elif open_sky is not None and open_sky < hdr.OPEN_SKY_WARN:
        log.warning("estimate_light: of the upper hemisphere, %.1f%% is seen at the placement "
                    "but only %.1f%% is open sky (step 1's learned background; warned below "
                    "%.0f%%): the rest is surfels. If the scene is outdoors, the placement looks "
                    "up through surfels the cameras saw against the sky (measured on "
                    "forward-facing captures with 2-3%% open sky: the light 35-141 deg "
                    "off, E(sun)/E(up) 37-84%% low); give the map (compose --env) or capture "
                    "views that look around", 100 * sky_seen, 100 * open_sky,
                    100 * hdr.OPEN_SKY_WARN)
    elif sky_clip > hdr.CLIPPED_SKY_WARN:
        log.warning("estimate_light: %.1f%% of the observed sky is clipped at EV 0 (warned "
                    "above %.0f%%): its light's power, and where in it the light is, cannot be "
                    "read from one exposure (measured through step 1: E(sun)/E(up) off by "
                    "31-35%% there); a "
                    "capture exposed for the sky avoids it", 100 * sky_clip,
                    100 * hdr.CLIPPED_SKY_WARN)

    t = time.perf_counter()
    label, p_outdoor = scene_label.resolve_label(
        cfg.label, rgb, mask, None if cfg.scene_label == "default" else cfg.scene_label)
    if p_outdoor is not None:
        log.info("estimate_light: label 'auto' -> %r (p(outdoor) = %.2f)", label, p_outdoor)
    timings["label"] = time.perf_counter() - t

    t = time.perf_counter()
    evs = tuple(float(e) for e in cfg.evs)
    ldrs = backend.complete(rgb, normal, mask, evs=evs, label=LABELS[label])
    timings["completion"] = time.perf_counter() - t

    t = time.perf_counter()
    ldrs = {float(k): np.asarray(v, np.float32) for k, v in ldrs.items()}
    radiance = np.asarray(hdr.fuse_brackets(ldrs, evs), np.float32)              # [H, W, 3]
    if not np.isfinite(radiance).all():
        raise ValueError(f"estimate_light: the backend {type(backend).__name__} produced "
                         f"non-finite values")
    timings["fusion"] = time.perf_counter() - t

    t = time.perf_counter()
    head = _load_head(cfg.light_head)
    lobes, regions, f = [], [], 1
    if head is not None:
        f = head_factor(trace, int(cfg.light_head_rows))
        pred = light_head.predict_lobes(*light_head.downsample_clipped(rgb, mask, f), head,
                                        LABELS[label])
        for lb in pred:                                      # regions back at full size
            lb["region"] = np.repeat(np.repeat(lb["region"], f, 0), f, 1)
        before = radiance
        radiance, lobes = light_head.add_lights(radiance, pred,
                                                trust_brackets=cfg.light_trust_brackets)
        radiance = radiance.astype(np.float32)
        regions = light_head.describe_regions(pred, before, radiance, cfg.light_trust_brackets)
    timings["light_head"] = time.perf_counter() - t

    t = time.perf_counter()
    radiance, sun = _sun_from_shadows(scene, space, radiance, mask > 0.5, cfg,
                                      sky_seen < hdr.SEEN_SKY_WARN)
    timings["sun_fit"] = time.perf_counter() - t

    t = time.perf_counter()
    oct_map = envmap.equirect_to_oct_np(radiance, int(cfg.oct_res)).astype(np.float32)
    timings["octahedral"] = time.perf_counter() - t
    t = time.perf_counter()
    lights = hdr.extract_lights(radiance, k=int(cfg.n_lights))
    for l in lights:             # the brightest regions need not be lights: a white wall
        l["above_white"] = bool(l["peak_luminance"] > 1.0)     # EV-0 white = 1 (its peak:
                                                               # a region can take in a wall)
    timings["lights"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0

    meta = {"source": source, "position": trace["meta"]["position"], "label": label,
            "label_requested": cfg.label, "p_outdoor": p_outdoor,
            "evs": list(evs), "backend": _backend_name(backend), "colour_space": space,
            "coverage": cov, "seen_sky_fraction": sky_seen, "open_sky_fraction": open_sky,
            "clipped_sky_fraction": sky_clip, "nonfinite_pixels": n_bad,
            "saturation_limit": hdr.saturation_limit(evs), "config": _config_dict(cfg),
            "trace": jsonable(trace["meta"]), "radiance": "linear",
            "layout": {"hdr": "equirect", "oct": "octahedral"}}
    meta["light_head"] = None if head is None else str(cfg.light_head)
    meta["scene_label_model"] = str(cfg.scene_label) if p_outdoor is not None else None
    meta["light_trust_brackets"] = None if head is None else float(cfg.light_trust_brackets)
    meta["light_head_block"] = f             # the head read the panorama in f×f blocks
    meta["sun_from_shadows"] = sun
    dom = meta["light_dominance"] = light_head.dominance(regions)
    if dom is not None and dom < light_head.DOMINANCE_MARGIN:
        log.warning("estimate_light: the strongest observed clipped light is %.2fx the next: "
                    "which dominates, so where shadows point, is a near tie", dom)
    return {"hdr": radiance, "oct": oct_map, "ldrs": ldrs,
            "input": {"rgb": rgb, "normal": normal, "mask": mask},
            "lights": lights, "lobes": lobes, "light_regions": regions, "coverage": cov,
            "timings": timings, "meta": meta}


def _sun_from_shadows(scene, space: str, radiance, observed, cfg: EstimateConfig,
                      loud: bool = False):
    """(radiance, record): the panorama with the sun fitted to the scene's cast shadows
    added where it did not observe it (``lighting.sun_fit``), and what was found and done
    (None when off). ``loud``: say it as a warning (the capture barely saw the sky)."""
    say = log.warning if loud else log.info
    if cfg.sun_from_shadows == "off":
        return radiance, None
    shapes = [sh for sh in scene.shapes() if hasattr(sh, "params")]
    if len(shapes) != 1:
        return radiance, {"action": f"skipped: {len(shapes)} surfels shapes (one expected)"}
    fit = sun_fit.fit_sun_in_scene(scene, shapes[0].params, space)
    rec = fit.as_dict()
    if not fit.usable:
        say("estimate_light: no sun from the scene's shadows: %s", fit.reason)
        rec["action"] = "none: " + fit.reason
        return radiance, rec
    radiance, rec["action"] = sun_fit.add_sun(radiance, observed, fit, cfg.sun_radius_deg)
    say("estimate_light: sun from the scene's shadows (%s): %s", fit.reason, rec["action"])
    return np.asarray(radiance, np.float32), rec


def _background_dir(spec: str, source) -> Path | None:
    """The run folder whose learned background to use, or None."""
    if spec == "none":
        return None
    if spec == "auto":
        if not isinstance(source, (str, Path)):
            return None
        d = Path(source).parent
        return d if (d / bgenv.FILE).is_file() else None
    d = Path(spec)
    if not d.exists():
        raise FileNotFoundError(f"estimate_light: background {spec!r}: no such folder "
                                f"(expected a step-1 run folder with {bgenv.FILE})")
    d = d if d.is_dir() else d.parent
    if not (d / bgenv.FILE).is_file():
        raise FileNotFoundError(f"estimate_light: background {spec!r}: no {bgenv.FILE} in {d}")
    mine = _run_data(Path(source).parent) if isinstance(source, (str, Path)) else None
    theirs = _run_data(d)
    if mine is not None and theirs is not None and mine != theirs:
        log.warning("estimate_light: the background comes from %s, whose capture (%s) is not "
                    "the scene's (%s): its sky is another scene's", d, theirs, mine)
    return d


def _run_data(run_dir: Path) -> str | None:
    """The dataset a step-1 run folder was trained on (its ``run.json``), or None."""
    try:
        return str(Path(read_run_info(run_dir)["data"]).resolve())
    except (OSError, ValueError, KeyError):
        return None


def add_background(trace: dict, run_dir, clipped_max_texels: float = np.inf) -> dict:
    """``trace`` with step 1's learned background (``train.background``) behind the surfels,
    where the capture saw it (:func:`comgs_dr.surfels.panorama.composite_background`), and
    white where the capture saw it clipped, in the connected parts of that record up to
    ``clipped_max_texels`` of the background's texels (:func:`small_parts`)."""
    rad, obs = bgenv.load(run_dir)
    H, W = trace["alpha"].shape
    rad_eq = envmap.oct_to_equirect_np(rad, W)                                   # [H, W, 3]
    obs_eq = envmap.oct_to_equirect_np(np.repeat(obs[..., None], 3, -1), W)[..., 0]
    if rad_eq.shape[:2] != (H, W):
        raise ValueError(f"estimate_light: the panorama must be 2:1 to add a background, got "
                         f"{W}x{H}")
    clipped = bgenv.load_clipped(run_dir)
    clip_eq = None if clipped is None else small_parts(
        bgenv.splat_record(clipped, H, W),
        float(clipped_max_texels) * 4.0 * np.pi / rad.shape[0] ** 2)            # [H, W, 3]
    out = panorama.composite_background(trace, rad_eq, obs_eq, clip_eq)
    out["meta"]["background"] = str(run_dir)
    out["meta"]["background_clipped"] = None if clipped is None else int(
        ((clip_eq.max(-1) >= 0.5) & (obs_eq > 0)).sum())
    if clipped is not None and out["meta"]["background_clipped"]:
        out["meta"]["clipped_pixel_rad"] = float(np.median(clipped["radius"]) * np.sqrt(np.pi))
    if clipped is None:
        log.info("estimate_light: %s has no %s (a step-1 run from before it existed): a sun "
                 "the capture saw clipped may read below white; re-run step 1 to record it",
                 run_dir, bgenv.CLIPPED_FILE)
    else:
        log.info("estimate_light: %d panorama pixels drawn at white from %d clipped capture "
                 "rays (%s)", out["meta"]["background_clipped"], len(clipped["directions"]),
                 bgenv.CLIPPED_FILE)
    return out


def head_factor(trace: dict, max_rows: int = 0) -> int:
    """Block size f (a power of 2 dividing the panorama) at which the light head reads the
    panorama: the smallest that brings it to at most ``max_rows`` rows (0: no limit), and
    coarser where step 1's clipped record (``add_background``) was drawn at a coarser pixel;
    halved until it divides H and W (a panorama of odd height is read at full size).

    The record knows clipping only at the capture's pixel size, and the head reads a region's
    size in panorama pixels (trained on panoramas where a sun is 1–4 pixels), so the panorama
    is coarsened until its pixels are about the capture's (``lights.downsample_clipped``).
    ``benchmarks/recon_light_e2e.py``, 64-px captures (0.65° pixels): at 1024×512 the sunrise
    sun's 0.003 sr region is 83 pixels and the head predicted 36–41× where the truth is 62×;
    at 512×256 (20 pixels) 55× of 86×.

    ``max_rows`` (``EstimateConfig.light_head_rows``, 256): the head is least accurate at 512
    rows. ``benchmarks/light_head_rows.py`` (the 5 held-out maps at 1024×512, 6 draws each,
    the mean |log(predicted / true power)| of the clipped regions): 0.64 with the head at 512
    rows, 0.55 / 0.55 / 0.64 at 256 / 128 / 64 (blender_sunrise −0.96 at 512, −0.30 at 256).
    """
    h, w = trace["alpha"].shape
    f = 1
    if max_rows and h > max_rows:
        f = 2 ** int(np.ceil(np.log2(h / max_rows)))
    side = trace["meta"].get("clipped_pixel_rad")
    if side and np.isfinite(side):
        f = max(f, 2 ** max(0, int(round(np.log2(side / (2 * np.pi / w))))))
    while f > 1 and (h % f or w % f):
        f //= 2
    return f


def small_parts(clipped: np.ndarray, max_sr: float) -> np.ndarray:
    """The record ``clipped`` [H, W, 3] (equirect) kept only in its connected parts (≥ ½ in
    any channel, ``hdr.label_equirect``) of solid angle ≤ ``max_sr``; zero elsewhere.

    An option, off by default (inf). It was the default while the record was kept per
    texel: a 1.6° texel record joined patches of bright sky into one 0.5–1.5 sr region whose
    gain the light head over-predicted (forest_slope 5.4× vs 2.7×, dominant light 76° off).
    With the record kept per ray (the capture's own pixels) a 16-texel limit measured no
    better (``benchmarks/recon_light_e2e.py``, 7 maps, E(sun)/E(up) within 25 % on 5 and 5 at
    512×256, 4 and 4 at 1024×512) and turned forest_slope's dominant light 54° away (5°
    with the whole record)."""
    if not np.isfinite(max_sr):
        return clipped
    on = clipped.max(-1) >= 0.5                                                  # [H, W]
    lab, n = hdr.label_equirect(on)
    if n == 0:
        return clipped
    h, w = on.shape
    area = np.bincount(lab.ravel(), np.broadcast_to(pixel_solid_angles(h, w), (h, w)).ravel(),
                       n + 1)                                                    # [n + 1]
    keep = area <= max_sr
    keep[0] = False
    return np.where(keep[lab][..., None], clipped, 0.0)


def _config_dict(cfg: EstimateConfig) -> dict:
    """``cfg`` as plain Python values (tuples as lists) that ``EstimateConfig(**d)`` takes
    back; an infinite ``clipped_max_texels`` stays inf here and is written as null."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(cfg).items()}


def check_model_files(cfg: EstimateConfig) -> None:
    """FileNotFoundError for a light head or scene-label model that ``cfg`` names and that
    does not exist."""
    if cfg.light_head not in ("default", "none") and not Path(cfg.light_head).is_file():
        raise FileNotFoundError(f"estimate_light: light head not found: {cfg.light_head}")
    if cfg.scene_label != "default" and not Path(cfg.scene_label).is_file():
        raise FileNotFoundError(f"estimate_light: scene-label model not found: "
                                f"{cfg.scene_label}")


def _load_head(spec: str):
    """The light head of ``EstimateConfig.light_head`` (None for "none", or for "default"
    when the shipped weights are absent: warned)."""
    if spec == "none":
        return None
    if spec == "default":
        if not light_head.DEFAULT_HEAD.is_file():
            log.warning("estimate_light: no shipped light head (%s); clipped lights keep the "
                        "brackets' power", light_head.DEFAULT_HEAD)
            return None
        return light_head.load_head()
    return light_head.load_head(spec)


def _backend_name(backend) -> str:
    kind = getattr(backend, "kind", None) or getattr(backend, "name", None)
    return type(backend).__name__ + (f"({kind})" if kind else "")
