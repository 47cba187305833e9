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
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import mitsuba as mi
import numpy as np

from comgs_dr.core.equirect import coverage, equirect_directions, pixel_solid_angles
from comgs_dr.lighting import backends, clear_sky, envmap, hdr, scene_label, sun_fit
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
           "backend_input", "estimate_light", "write_outputs", "output_paths", "preview_image",
           "sky_warning", "BackendConfig", "make_backend", "PlacementEstimateConfig",
           "PlacementEstimator", "placement_estimator"]

LOW_COVERAGE = 0.4      # the paper's smallest evaluated coverage (Appendix, Table supp_lgt)


@dataclass
class EstimateConfig:
    """Settings of :func:`estimate_light`.

    width, height: size of the traced panorama in pixels, 2:1 (default 1024 × 512).
    max_hits: surfels composited per panorama ray (default 32).
    exclude_radius: surfels closer than this to the position are left out (the object
        itself), in scene units (default 0).
    label: the scene label that conditions the completion and the light head: "auto"
        (default: classified from the trace, ``lighting.scene_label``), "outdoor",
        "indoor" or "unknown".
    evs: exposures of the completion in EV, distinct, ≤ 0, 0 among them (default 0, −2.5, −5).
    oct_res: side of the octahedral map in texels (default 512).
    net_resolution: (H, W) input size of the default network backend (None: the size its
        weights were trained at, ``NetworkBackend``'s default).
    supersample: rays per pixel side of the trace (default 1).
    colour_space: space of the radiance field's colour, "srgb" or "linear"; None (default):
        the PLY's recorded space, or "srgb" for a scene object.
    n_lights: brightest regions reported as lights (``hdr.extract_lights``; default 3).
    light_head: weights of the light head: "default" (the shipped ones, skipped with a
        warning if absent), "none" (no head), or a file.
    scene_label: the classifier of label "auto": "default" (the shipped one) or a model from
        ``comgs train-scene-label``.
    light_head_rows: the head reads the panorama at most this many rows (``head_factor``;
        default 256; 0: no limit).
    light_trust_brackets: in [0, 1], the brackets' vote on which clipped region holds the
        head's power (``lights.add_lights``; default ``lights.TRUST_BRACKETS``).
    background: step 1's learned sky behind the surfels: "auto" (default: the PLY's run
        folder, if it has one), "none", or a run folder.
    clipped_max_texels: step 1's record of clipped sky (``add_background``) is applied to its
        connected parts of up to this many background texels (default inf: all; 0: none).
    sun_from_shadows: "auto" (default): fit a sun to the scene's own cast shadows
        (``lighting.sun_fit``) and add it where the panorama did not observe its direction;
        "off".
    sun_radius_deg: angular radius of the sun added from the shadows, in degrees, in (0, 10]
        (default 1).
    unseen_sky: when a sun the panorama did not see is added from the shadows, the sky the
        capture did not see either: "clear" (default: a clear sky's shape and colour for that
        sun at the completion's luminance, ``lighting.clear_sky``) or "completion" (the
        completion's guess, which takes the ground's colour).
    sky_turbidity: the clear sky's turbidity, in [1, 10] (1.5 very clear … 10 hazy), or 0
        (default): the one at which the sky model's sun/sky ratio is the shadows' k
        (``clear_sky.turbidity_for``: the shadows' contrast says how hazy the sky is).
    max_ground_albedo: the unseen sky (with that sun, or where the capture saw under
        ``hdr.SEEN_SKY_WARN`` of the upper hemisphere and no sun was added) is raised until
        the surroundings below the horizon reflect at most this fraction of the light above
        (E_down / E_up per channel, ``clear_sky.ground_albedo_floor``; default
        ``clear_sky.MAX_GROUND_ALBEDO`` 0.3; 0: off).
    """
    width: int = 1024
    height: int = 512
    max_hits: int = 32
    exclude_radius: float = 0.0
    label: str = "auto"
    evs: tuple = (0.0, -2.5, -5.0)
    oct_res: int = 512
    net_resolution: tuple | None = None
    supersample: int = 1
    colour_space: str | None = None
    n_lights: int = 3
    light_head: str = "default"
    scene_label: str = "default"
    light_head_rows: int = 256
    light_trust_brackets: float = TRUST_BRACKETS
    background: str = "auto"
    clipped_max_texels: float = float("inf")
    sun_from_shadows: str = "auto"
    sun_radius_deg: float = 1.0
    unseen_sky: str = "clear"
    sky_turbidity: float = 0.0
    max_ground_albedo: float = clear_sky.MAX_GROUND_ALBEDO

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
        if self.unseen_sky not in ("clear", "completion"):
            raise ValueError(f"EstimateConfig.unseen_sky must be 'clear' or 'completion', got "
                             f"{self.unseen_sky!r}")
        if isinstance(self.sky_turbidity, bool) or not (
                float(self.sky_turbidity) == 0.0 or 1.0 <= float(self.sky_turbidity) <= 10.0):
            raise ValueError(f"EstimateConfig.sky_turbidity must be 0 (from the shadows) or in "
                             f"[1, 10], got "
                             f"{self.sky_turbidity!r}")
        if isinstance(self.max_ground_albedo, bool) \
                or not 0.0 <= float(self.max_ground_albedo) <= 1.0:
            raise ValueError(f"EstimateConfig.max_ground_albedo must be in [0, 1], got "
                             f"{self.max_ground_albedo!r}")
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
    ``timings`` {load, trace, label, completion, fusion, light_head, sun_fit, octahedral,
    lights, total} in seconds and ``meta``.
    Errors: see the module docstring.

    Phases: load, trace, the observed part (:func:`_observed_trace`, :func:`_coverage_of`,
    :func:`_report_sky`), label, completion, fusion, light head
    (:func:`_apply_light_head`), sun from the shadows, octahedral map, lights, meta.
    """
    cfg = EstimateConfig() if cfg is None else cfg
    cfg.validate()
    check_model_files(cfg)                      # before the trace, not minutes into it
    t0 = time.perf_counter()
    timings = {}
    scene, space, source = _open_scene(scene_or_ply_path, cfg.colour_space)
    if backend is None:
        backend = default_backend(resolution=cfg.net_resolution)
    timings["load"] = time.perf_counter() - t0
    with _timed(timings, "trace"):
        trace = _trace(scene, position, cfg.panorama_config(space), source)
    trace, n_bad, bg_dir = _observed_trace(trace, cfg, scene_or_ply_path)
    rgb, normal, mask = backend_input(trace)
    cov = _coverage_of(mask, trace, source, cfg.exclude_radius)
    sky = _sky_fractions(trace, rgb, mask)
    _report_sky(sky, _sky_fix(bg_dir, cfg.background, scene_or_ply_path))
    with _timed(timings, "label"):
        label, p_outdoor = _resolve_label(cfg, rgb, mask)
    with _timed(timings, "completion"):
        evs = tuple(float(e) for e in cfg.evs)
        ldrs = backend.complete(rgb, normal, mask, evs=evs, label=LABELS[label])
    with _timed(timings, "fusion"):
        ldrs, radiance = _fuse(ldrs, evs, backend)
    with _timed(timings, "light_head"):
        head, radiance, lobes, regions, f = _apply_light_head(radiance, rgb, mask, trace, label,
                                                               cfg)
    with _timed(timings, "sun_fit"):
        radiance, sun = _sun_from_shadows(scene, space, radiance, mask > 0.5, cfg,
                                          sky["seen"] < hdr.SEEN_SKY_WARN, ldr=rgb)
        radiance, lift = _unseen_sky_level(radiance, mask > 0.5, sky, sun, cfg)
    with _timed(timings, "octahedral"):
        oct_map = envmap.equirect_to_oct_np(radiance, int(cfg.oct_res)).astype(np.float32)
    with _timed(timings, "lights"):
        lights = _lights(radiance, int(cfg.n_lights))
    timings["total"] = time.perf_counter() - t0
    meta = _meta(cfg, source=source, trace=trace, label=label, p_outdoor=p_outdoor, evs=evs,
                 backend=backend, space=space, coverage=cov, sky=sky, n_bad=n_bad, head=head,
                 block=f, sun=sun, regions=regions)
    meta["unseen_sky_lift"] = lift
    return {"hdr": radiance, "oct": oct_map, "ldrs": ldrs,
            "input": {"rgb": rgb, "normal": normal, "mask": mask},
            "lights": lights, "lobes": lobes, "light_regions": regions, "coverage": cov,
            "timings": timings, "meta": meta}


@contextmanager
def _timed(timings: dict, name: str):
    """``timings[name]``: the seconds the ``with`` block took (not set if it raised)."""
    t = time.perf_counter()
    yield
    timings[name] = time.perf_counter() - t


def _open_scene(scene_or_ply_path, colour_space: str | None):
    """(Mitsuba scene, colour space, source name) of a PLY path or a loaded scene."""
    if isinstance(scene_or_ply_path, (str, Path)):
        scene, space = load_scene(scene_or_ply_path)
        source = str(scene_or_ply_path)
    else:
        scene, space, source = scene_or_ply_path, "srgb", "<scene>"
    return scene, colour_space or space, source


def _trace(scene, position, pcfg: PanoramaConfig, source: str) -> dict:
    """``panorama.trace_panorama``; its ValueError (a bad position or exclusion radius)
    re-raised with the scene and the position."""
    try:
        return panorama.trace_panorama(scene, position, pcfg)
    except ValueError as exc:
        raise ValueError(f"estimate_light: cannot trace the scene {source} at "
                         f"{np.asarray(position).tolist()}: {exc}") from exc


def _observed_trace(trace: dict, cfg: EstimateConfig, scene_or_ply_path):
    """(trace, non-finite pixel count, background run folder or None): the trace with its
    non-finite pixels unobserved (warned) and step 1's learned sky behind the surfels."""
    trace, n_bad = sanitize_trace(trace)
    if n_bad:
        log.warning("estimate_light: %d traced pixels hold NaN/Inf (degenerate surfels?); "
                    "they are treated as unobserved", n_bad)
    bg_dir = _background_dir(cfg.background, scene_or_ply_path)
    if bg_dir is not None:
        trace = add_background(trace, bg_dir, cfg.clipped_max_texels)
    return trace, n_bad, bg_dir


def _coverage_of(mask, trace: dict, source: str, exclude_radius: float) -> float:
    """The observed solid-angle fraction; ValueError when it is zero, a warning below
    ``LOW_COVERAGE``."""
    cov = _coverage(mask)
    if cov <= 0.0:
        raise ValueError(
            f"estimate_light: zero coverage at {trace['meta']['position']}: no surfel of "
            f"{source} is visible from there ({trace['meta']['surfels']} traced, "
            f"{trace['meta']['excluded']} excluded by exclude_radius={exclude_radius}). "
            f"Move the position, lower exclude_radius, or check the scene")
    if cov < LOW_COVERAGE:
        log.warning("estimate_light: coverage %.1f%% is below %.0f%% (the paper's tested "
                    "range); the completion is mostly guessed", 100 * cov, 100 * LOW_COVERAGE)
    return cov


def _sky_fractions(trace: dict, rgb, mask) -> dict:
    """Of the upper hemisphere: ``seen`` (observed at all), ``clipped`` (of the observed,
    clipped at EV 0), ``open`` (step 1's learned background, the sky itself; None
    without one)."""
    seen = hdr.seen_sky_fraction(mask)
    clipped = hdr.clipped_sky_fraction(rgb, mask)
    open_sky = (hdr.seen_sky_fraction(trace["background_alpha"])
                if "background_alpha" in trace else None)
    return {"seen": seen, "clipped": clipped, "open": open_sky}


def _sky_fix(bg_dir, background: str, scene_or_ply_path) -> str:
    """What to do about a sky the capture barely saw, given where the sky came from."""
    if bg_dir is not None:
        return "add views that see the sky, or give the map (compose --env)"
    if background == "none" and _background_dir("auto", scene_or_ply_path):
        return "the run has a learned sky that background 'none' left out: use the default " \
               "background 'auto'"
    return "if the capture saw the sky, reconstruct with --background env (step 1 " \
           "keeps no sky without it); else add sky views or give the map (compose --env)"


def _report_sky(sky: dict, fix: str) -> None:
    """Log how much of the sky the trace holds, and :func:`sky_warning`'s warning if any."""
    if sky["open"] is not None:
        log.info("estimate_light: %.1f%% of the upper hemisphere is observed, %.1f%% is open "
                 "sky (step 1's learned background), the rest surfaces", 100 * sky["seen"],
                 100 * sky["open"])
    warning = sky_warning(sky["seen"], sky["open"], sky["clipped"], fix)
    if warning:
        log.warning(warning)


def sky_warning(seen: float, open_sky: float | None, clipped: float, fix: str) -> str | None:
    """The warning about the sky at the placement, or None: the capture saw too little of
    the upper hemisphere (below ``hdr.SEEN_SKY_WARN``; ``fix`` says what to do), or little
    of what it saw is open sky (below ``hdr.OPEN_SKY_WARN``), or too much of the observed
    sky is clipped at EV 0 (above ``hdr.CLIPPED_SKY_WARN``). Fractions in [0, 1]."""
    if seen < hdr.SEEN_SKY_WARN:
        return ("estimate_light: the capture saw %.1f%% of the upper hemisphere (sky, "
                "ceiling, anything above the horizon) at the placement (warned below "
                "%.0f%%): the lights up there are the completion's guess (measured through "
                "step 1 without sky views: E(sun)/E(up) 23-81%% low, the light 40-46 deg "
                "off), but for a sun the scene's cast shadows show (sun_from_shadows, "
                "reported next; the demo without sky views: 3.5 deg off, the sky's power "
                "still 0.57x); %s" % (100 * seen, 100 * hdr.SEEN_SKY_WARN, fix))
    if open_sky is not None and open_sky < hdr.OPEN_SKY_WARN:
        return ("estimate_light: of the upper hemisphere, %.1f%% is seen at the placement "
                "but only %.1f%% is open sky (step 1's learned background; warned below "
                "%.0f%%): the rest is surfels. If the scene is outdoors, the placement looks "
                "up through surfels the cameras saw against the sky (measured on "
                "forward-facing captures with 2-3%% open sky: the light 35-141 deg "
                "off, E(sun)/E(up) 37-84%% low); give the map (compose --env) or capture "
                "views that look around" % (100 * seen, 100 * open_sky,
                                            100 * hdr.OPEN_SKY_WARN))
    if clipped > hdr.CLIPPED_SKY_WARN:
        return ("estimate_light: %.1f%% of the observed sky is clipped at EV 0 (warned "
                "above %.0f%%): its light's power, and where in it the light is, cannot be "
                "read from one exposure (measured through step 1: E(sun)/E(up) off by "
                "31-35%% there); a "
                "capture exposed for the sky avoids it" % (100 * clipped,
                                                           100 * hdr.CLIPPED_SKY_WARN))
    return None


def _resolve_label(cfg: EstimateConfig, rgb, mask) -> tuple[str, float | None]:
    """(label, p(outdoor) or None): ``cfg.label``, or with "auto" the classifier's answer."""
    label, p_outdoor = scene_label.resolve_label(
        cfg.label, rgb, mask, None if cfg.scene_label == "default" else cfg.scene_label)
    if p_outdoor is not None:
        log.info("estimate_light: label 'auto' -> %r (p(outdoor) = %.2f)", label, p_outdoor)
    return label, p_outdoor


def _fuse(ldrs: dict, evs: tuple, backend) -> tuple[dict, np.ndarray]:
    """(completions as float32 {ev: [H, W, 3]}, their HDR fusion [H, W, 3]); ValueError
    when the backend's output does not fuse to finite values."""
    ldrs = {float(k): np.asarray(v, np.float32) for k, v in ldrs.items()}
    radiance = np.asarray(hdr.fuse_brackets(ldrs, evs), np.float32)              # [H, W, 3]
    if not np.isfinite(radiance).all():
        raise ValueError(f"estimate_light: the backend {type(backend).__name__} produced "
                         f"non-finite values")
    return ldrs, radiance


def _apply_light_head(radiance, rgb, mask, trace: dict, label: str, cfg: EstimateConfig):
    """(head or None, radiance, lobes, regions, block size f): the light head's power added
    to the lights clipped at EV 0, read from the panorama in f×f blocks (``head_factor``)."""
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
    return head, radiance, lobes, regions, f


def _lights(radiance, n: int) -> list[dict]:
    """The ``n`` brightest regions (``hdr.extract_lights``), each marked ``above_white``
    where its peak is above the EV-0 white (1): a light, where a white wall stays below."""
    lights = hdr.extract_lights(radiance, k=n)
    for l in lights:             # the brightest regions need not be lights: a white wall
        l["above_white"] = bool(l["peak_luminance"] > 1.0)     # EV-0 white = 1 (its peak:
                                                               # a region can take in a wall)
    return lights


def _meta(cfg: EstimateConfig, *, source, trace, label, p_outdoor, evs, backend, space,
          coverage, sky, n_bad, head, block, sun, regions) -> dict:
    """The result's ``meta`` (what was asked, found and done); warns when the strongest
    clipped light is a near tie with the next (where shadows point is then uncertain)."""
    meta = {"source": source, "position": trace["meta"]["position"], "label": label,
            "label_requested": cfg.label, "p_outdoor": p_outdoor,
            "evs": list(evs), "backend": _backend_name(backend), "colour_space": space,
            "coverage": coverage, "seen_sky_fraction": sky["seen"],
            "open_sky_fraction": sky["open"], "clipped_sky_fraction": sky["clipped"],
            "nonfinite_pixels": n_bad,
            "saturation_limit": hdr.saturation_limit(evs), "config": _config_dict(cfg),
            "trace": jsonable(trace["meta"]), "radiance": "linear",
            "layout": {"hdr": "equirect", "oct": "octahedral"}}
    meta["light_head"] = None if head is None else str(cfg.light_head)
    meta["scene_label_model"] = str(cfg.scene_label) if p_outdoor is not None else None
    meta["light_trust_brackets"] = None if head is None else float(cfg.light_trust_brackets)
    meta["light_head_block"] = block         # the head read the panorama in f×f blocks
    meta["sun_from_shadows"] = sun
    dom = meta["light_dominance"] = light_head.dominance(regions)
    if dom is not None and dom < light_head.DOMINANCE_MARGIN:
        log.warning("estimate_light: the strongest observed clipped light is %.2fx the next: "
                    "which dominates, so where shadows point, is a near tie", dom)
    return meta


def _sun_from_shadows(scene, space: str, radiance, observed, cfg: EstimateConfig,
                      loud: bool = False, ldr=None):
    """(radiance, record): the panorama with the sun fitted to the scene's cast shadows
    (``lighting.sun_fit``), and what was found and done (None when off). A sun the
    panorama did not observe is added; a sun it saw clipped in ``ldr`` (the EV-0 display
    trace [H, W, 3]) keeps its direction and gets its power and colour from the shadows
    toward it (a clipped sun's are the light head's guess); a sun it saw unclipped is
    kept. ``loud``: say it as a warning (the capture barely saw the sky)."""
    say = log.warning if loud else log.info
    if cfg.sun_from_shadows == "off":
        return radiance, None
    shapes = [sh for sh in scene.shapes() if hasattr(sh, "params")]
    if len(shapes) != 1:
        return radiance, {"action": f"skipped: {len(shapes)} surfels shapes (one expected)"}
    receivers = sun_fit.scene_receivers(scene, shapes[0].params, space)
    fit = sun_fit.fit_sun(*receivers)
    rec = fit.as_dict()
    if not fit.usable:
        say("estimate_light: no sun from the scene's shadows: %s", fit.reason)
        rec["action"] = "none: " + fit.reason
        return radiance, rec
    seen = sun_fit.seen_sun(radiance, observed, fit.direction)
    if seen is not None and ldr is not None:
        radiance, rec["seen"], rec["action"] = _seen_sun(radiance, receivers, seen, ldr)
    else:
        radiance, rec["action"] = sun_fit.add_sun(radiance, observed, fit, cfg.sun_radius_deg,
                                                  unseen_sky=cfg.unseen_sky,
                                                  turbidity=float(cfg.sky_turbidity) or None,
                                                  max_ground_albedo=float(cfg.max_ground_albedo))
    say("estimate_light: sun from the scene's shadows (%s): %s", fit.reason, rec["action"])
    return np.asarray(radiance, np.float32), rec


def _unseen_sky_level(radiance, observed, sky: dict, sun, cfg: EstimateConfig):
    """(radiance, record or None): where the capture saw little of the upper hemisphere
    (below ``hdr.SEEN_SKY_WARN``) and no sun was added from the shadows (``add_sun`` lifts
    its own sky), the completion's unseen sky raised until the ground reflects at most
    ``cfg.max_ground_albedo`` of the light above (``clear_sky.lift_unseen_sky``)."""
    added = sun is not None and str(sun.get("action", "")).startswith("added")
    if cfg.max_ground_albedo <= 0 or added or sky["seen"] >= hdr.SEEN_SKY_WARN:
        return radiance, None
    out, s, implied = clear_sky.lift_unseen_sky(radiance, observed, float(cfg.max_ground_albedo))
    rec = {"lift": s, "implied_albedo_before": [float(a) for a in implied],
           "max_ground_albedo": float(cfg.max_ground_albedo)}
    if s > 1.0:
        log.warning("estimate_light: the unseen sky raised %.2fx: below it the ground reflected "
                    "%s of the light above (at most %.2f allowed, --max-ground-albedo)%s", s,
                    ", ".join(f"{a:.2f}" for a in implied), cfg.max_ground_albedo,
                    " (the most it is raised)" if s >= clear_sky.MAX_LIFT else "")
    return np.asarray(out, np.float32), rec


#: EV-0 display value from which a seen sun counts as clipped (its power then guessed)
SUN_CLIPPED = 0.98


def _seen_sun(radiance, receivers, direction, ldr):
    """(radiance, record of the fit toward the seen sun or None, action) for a sun the
    panorama observed at ``direction``: rescaled to the shadows' k per channel when it was
    clipped in ``ldr`` and its shadow is evidence, else kept."""
    h, w = ldr.shape[:2]
    near = equirect_directions(h, w) @ direction >= np.cos(np.radians(3.0))
    if not (np.asarray(ldr)[near].max(-1) >= SUN_CLIPPED).any():
        return radiance, None, "kept: the panorama measured the sun (not clipped)"
    at = sun_fit.fit_sun(*receivers, direction=direction)
    if not at.usable:
        return radiance, at.as_dict(), "kept the seen sun's guessed power: " + at.reason
    radiance, action = sun_fit.rescale_seen_sun(radiance, at)
    return radiance, at.as_dict(), action


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
    ``max_rows``: ``EstimateConfig.light_head_rows`` (default 256).
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

    Off by default (``EstimateConfig.clipped_max_texels`` inf: the whole record is kept)."""
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


# ---------------------------------------------------------------------------------------
# The completion backend of `comgs estimate-light`

@dataclass
class BackendConfig:
    """The completion model of ``comgs estimate-light`` (``lighting.backends``).

    backend: "net+sh" (default: the shipped weights, their hole averaged with the SH fill,
        outdoors the weights' luminance in the average's colour), "net" (the weights alone),
        the fills "mean", "push_pull", "sh", or "diffusers".
    weights: completion-net checkpoint of backends net+sh and net (None: the shipped one).
    diffusers_dir: local diffusers inpainting model (backend diffusers); prompt embeddings
        come from its text encoder or DIR/ev_embeddings.pt ({'xi_b': [L, D], 'xi_d': [L, D]}).
    steps: diffusion steps of backend diffusers (default 30).
    """
    backend: str = "net+sh"
    weights: str | None = None
    diffusers_dir: str | None = None
    steps: int = 30


def make_backend(cfg: BackendConfig, net_resolution: tuple | None = None) -> CompletionBackend:
    """The completion backend ``cfg`` names; ``net_resolution`` (H, W): the network's input
    size (None: the size its weights were trained at). ValueError for a setting the backend
    would ignore (named by its ``estimate-light`` flag) or one it lacks."""
    net = cfg.backend in ("net", "net+sh")
    for flag, value, applies in (("--weights", cfg.weights, net),
                                 ("--net-resolution", net_resolution, net),
                                 ("--diffusers-dir", cfg.diffusers_dir,
                                  cfg.backend == "diffusers")):
        if value is not None and not applies:
            raise ValueError(f"{flag} does not apply to --backend {cfg.backend}")
    if net:
        res = tuple(net_resolution) if net_resolution else None
        model = backends.load_network_backend(cfg.weights, res)
        return model if cfg.backend == "net" else backends.net_sh_blend(model)
    if cfg.backend == "diffusers":
        if not cfg.diffusers_dir:
            raise ValueError("--backend diffusers needs --diffusers-dir DIR")
        return backends.DiffusersBackend.from_dir(cfg.diffusers_dir, steps=cfg.steps)
    return backends.FillBackend(cfg.backend)


# ---------------------------------------------------------------------------------------
# The light of each object of `comgs compose` (without --env)

@dataclass
class PlacementEstimateConfig:
    """How ``comgs compose`` estimates the light at each object's centre: the
    :class:`EstimateConfig` fields it sets (the others keep their defaults) and the
    completion weights.

    label: "auto" (default), "outdoor", "indoor" or "unknown" (``EstimateConfig.label``).
    scene_label: the classifier of label "auto" ("default": the shipped one).
    light_head: "default" (the shipped one), "none", or a file.
    sun_from_shadows: "auto" (default) or "off".
    unseen_sky: "clear" (default) or "completion" (``EstimateConfig.unseen_sky``).
    sky_turbidity: 0 (default: from the shadows) or in [1, 10] (``EstimateConfig``).
    max_ground_albedo: in [0, 1] (default 0.3; 0: off; ``EstimateConfig``).
    weights: completion-net checkpoint (None: the shipped one, its hole averaged with the SH
        fill, ``backends.default_backend``).
    """
    label: str = "auto"
    scene_label: str = "default"
    light_head: str = "default"
    sun_from_shadows: str = "auto"
    unseen_sky: str = "clear"
    sky_turbidity: float = 0.0
    max_ground_albedo: float = clear_sky.MAX_GROUND_ALBEDO
    weights: str | None = None


# the settings of PlacementEstimateConfig as `comgs compose` spells them, in the order a
# conflict with --env is reported
_PLACEMENT_FLAGS = (("label", "--label"), ("scene_label", "--scene-label"),
                    ("weights", "--weights"), ("light_head", "--light-head"),
                    ("sun_from_shadows", "--sun-from-shadows"), ("unseen_sky", "--unseen-sky"),
                    ("sky_turbidity", "--sky-turbidity"),
                    ("max_ground_albedo", "--max-ground-albedo"))


def placement_estimator(scene_run, out, env=None, say: Callable[[str], object] = log.info,
                        **settings) -> PlacementEstimator | None:
    """The ``estimator`` of ``stages.compose.compose``: None when ``env`` (one map lighting
    every object) is given, which no estimation ``settings`` may go with (ValueError);
    else a :class:`PlacementEstimator` with ``PlacementEstimateConfig(**settings)``.

    >>> est = placement_estimator("runs/scene", "comp", label="outdoor")   # doctest: +SKIP
    >>> compose("runs/scene", objects, "transform.json", "comp", estimator=est)  # doctest: +SKIP
    """
    if env is not None:
        for field, flag in _PLACEMENT_FLAGS:
            if field in settings:
                raise ValueError(f"{flag} sets up the lighting estimation; with --env the map "
                                 f"is the light and nothing is estimated")
        return None
    return PlacementEstimator(scene_run, out, PlacementEstimateConfig(**settings), say)


class PlacementEstimator:
    """``estimator(world position [3], object name) -> equirect radiance [H, W, 3]``:
    :func:`estimate_light` on the scene run's ``point_cloud.ply`` at the position, its files
    written to ``OUT/env/<name>_estimate/<name>.exr`` (:func:`write_outputs`) and named
    through ``say``. The settings and model files are checked when it is made, before
    anything is traced."""

    def __init__(self, scene_run, out, cfg: PlacementEstimateConfig,
                 say: Callable[[str], object] = log.info):
        self.scene_ply = str(Path(scene_run) / "point_cloud.ply")
        self.out, self.say = Path(out), say
        self.cfg = EstimateConfig(label=cfg.label or "auto",       # an empty value: the default
                                  scene_label=cfg.scene_label or "default",
                                  light_head=cfg.light_head or "default",
                                  sun_from_shadows=cfg.sun_from_shadows or "auto",
                                  unseen_sky=cfg.unseen_sky or "clear",
                                  sky_turbidity=cfg.sky_turbidity,
                                  max_ground_albedo=cfg.max_ground_albedo)
        self.cfg.validate()
        check_model_files(self.cfg)
        if cfg.weights is not None and not Path(cfg.weights).is_file():
            raise FileNotFoundError(f"--weights: completion weights not found: {cfg.weights} "
                                    f"(or estimate the map with `comgs estimate-light "
                                    f"--backend push_pull` and give it as --env)")
        self.backend = (backends.default_backend() if cfg.weights is None else
                        backends.net_sh_blend(backends.load_network_backend(cfg.weights)))

    def __call__(self, pos, name: str) -> np.ndarray:
        r = estimate_light(self.scene_ply, pos, self.cfg, self.backend)
        at = np.round(np.asarray(pos, float), 3).tolist()
        if r["meta"].get("p_outdoor") is not None:       # each placement is classified
            self.say(f"lighting at {at}: label "
                     f"auto -> {r['meta']['label']} (p(outdoor) {r['meta']['p_outdoor']:.2f})")
        paths = write_outputs(r, self.out / "env" / f"{name}_estimate" / f"{name}.exr")
        self.say(f"lighting of {name!r} at {at}: {paths['json']}, {paths['preview']}")
        return r["hdr"]
