"""Exposure and white balance between two captures: the per-channel gain that takes the
object capture's linear units to the scene capture's.

Photos are display values: ``v = sRGB(k ⊙ L)``, where ``L`` is the radiance and ``k`` the
capture's camera gain (exposure × white balance, one factor per channel; the tone curve is
taken to be the sRGB one and the photo unclipped). Every stage fits linear quantities after
the sRGB decode (``core.colorspace``), so within one capture everything is in that capture's
linear units ``k ⊙ L``. An object photographed with ``k_o`` and composed into a scene
photographed with ``k_s`` needs the gain ``g = k_s / k_o`` (3 channels) on what it carries
over from its own capture: its step-2 albedo where that absorbed the object capture's
exposure and colour cast (step 2 cannot tell albedo × light from a brighter, warmer albedo
under a duller, greyer light: its white-light prior sends a colour cast into the albedo).

What can be estimated, and from what (:func:`resolve_exposure`):

* ``reference`` (:func:`gain_from_reference`): a surface of one reflectance seen in a photo
  of each capture under the same light (a grey card; the floor the object stood on when it
  was photographed where it will be composed): ``g = p_s / p_o``, the ratio of the patch's
  mean linear colour (:func:`linear_patch`: each pixel sRGB-decoded, then averaged; clipped
  pixels left out) in the scene photo and in the object photo.
* ``given``: the user's own ``g`` (``--exposure-gain R G B``).
* ``grey-world`` (:func:`gain_from_grey_world`): white balance only, assuming the object's
  mean albedo is grey; its luminance is kept (no exposure information) and a truly coloured
  object is made grey on average: opt-in only.
* otherwise ``assumed``: g = 1, with :data:`NO_REFERENCE` saying so.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from comgs_dr.core.colorspace import LUMA, srgb_decode
from comgs_dr.data.images import read_image

METHODS = ("assumed", "given", "reference", "grey-world")
#: a display value at or above this (of 1) in any channel counts as clipped
CLIPPED = 254.5 / 255.0
#: at least this share of a patch's pixels must be unclipped
MIN_UNCLIPPED = 0.5
#: gains outside [1/GAIN_LIMIT, GAIN_LIMIT] are refused (a wrong patch, not a camera setting:
#: 2^±8 is 16 stops)
GAIN_LIMIT = 256.0

NO_REFERENCE = (
    "no exposure or white-balance reference: gain 1 assumed, i.e. the object's and the scene's "
    "photos share one exposure and white balance (the same camera settings), or the object's "
    "step 2 put its capture's exposure and colour cast into its learnt light and not into its "
    "albedo. If the object looks too bright, dark or tinted in the composite, give a grey card "
    "or support surface seen in both captures (--white-patch) or the gain (--exposure-gain)")
LINEARISED = ("photos decoded from sRGB (IEC 61966-2-1) to linear before averaging; the "
              "camera's tone curve taken to be sRGB's")


@dataclass
class ExposureGain:
    """The object → scene gain of one object and how it was found.

    gain: linear scene-capture units per object-capture unit, R, G, B.
    method: one of :data:`METHODS`.
    assumed: what the estimate rests on, in words (goes to composition.json and the report).
    detail: the measurements (patch colours, pixel counts, ...).
    """
    gain: tuple = (1.0, 1.0, 1.0)
    method: str = "assumed"
    assumed: str = NO_REFERENCE
    detail: dict = field(default_factory=dict)

    def __post_init__(self):
        g = np.asarray(self.gain, np.float64)
        if g.shape != (3,) or not np.isfinite(g).all() or (g <= 0).any():
            raise ValueError(f"exposure gain must be 3 finite positive numbers (R G B), got "
                             f"{self.gain!r}")
        if (g > GAIN_LIMIT).any() or (g < 1 / GAIN_LIMIT).any():
            raise ValueError(f"exposure gain {_fmt(g)} is beyond ×{GAIN_LIMIT:g} or "
                             f"×1/{GAIN_LIMIT:g} (16 stops): check the patches or the numbers")
        if self.method not in METHODS:
            raise ValueError(f"exposure method must be one of {', '.join(METHODS)}, got "
                             f"{self.method!r}")
        self.gain = tuple(float(v) for v in g)

    @property
    def is_identity(self) -> bool:
        return all(abs(v - 1.0) < 1e-9 for v in self.gain)

    @property
    def exposure_ev(self) -> float:
        """The gain's luminance in stops (EV): its exposure part."""
        return float(np.log2(LUMA @ np.asarray(self.gain)))

    @property
    def white_balance(self) -> tuple:
        """The gain over its luminance: its white-balance part (1, 1, 1 for none)."""
        g = np.asarray(self.gain)
        return tuple(float(v) for v in g / (LUMA @ g))

    def to_json(self) -> dict:
        return {"gain": [round(v, 6) for v in self.gain], "method": self.method,
                "exposure_ev": round(self.exposure_ev, 4),
                "white_balance": [round(v, 4) for v in self.white_balance],
                "assumed": self.assumed, **({"detail": self.detail} if self.detail else {})}

    def text(self) -> str:
        """One line for the command's output."""
        return (f"exposure gain {_fmt(self.gain)} ({self.method}; {self.exposure_ev:+.2f} EV, "
                f"white balance {_fmt(self.white_balance)})")


def _fmt(v) -> str:
    return "(" + ", ".join(f"{float(x):.3f}" for x in v) + ")"


# ----------------------------------------------------------------------------- patches

def parse_patch(spec) -> tuple[Path, tuple | None]:
    """``PHOTO`` or ``PHOTO:X0,Y0,X1,Y1`` (pixels, x right, y down, end exclusive) ->
    (path, box or None: the whole photo)."""
    s = str(spec)
    head, sep, tail = s.rpartition(":")
    if sep and tail.count(",") == 3:
        try:
            box = tuple(int(round(float(t))) for t in tail.split(","))
        except ValueError:
            raise ValueError(f"{s}: the patch box must be X0,Y0,X1,Y1 in pixels") from None
        return Path(head), box
    return Path(s), None


def linear_patch(path, box=None) -> dict:
    """The mean linear colour of the patch ``box`` (X0, Y0, X1, Y1; None: the whole photo)
    of a photo: every pixel sRGB-decoded, clipped pixels (a channel ≥ :data:`CLIPPED`) left
    out. Returns {"rgb", "pixels", "clipped", "box", "photo"}; ValueError (naming the photo)
    for a box outside it, more than half of it clipped, or a black patch."""
    img = read_image(path)[..., :3]
    h, w = img.shape[:2]
    x0, y0, x1, y1 = box if box is not None else (0, 0, w, h)
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise ValueError(f"{path}: patch box {x0},{y0},{x1},{y1} is not inside the "
                         f"{w}x{h} photo (X0,Y0,X1,Y1 with X0 < X1 <= {w}, Y0 < Y1 <= {h})")
    px = img[y0:y1, x0:x1].reshape(-1, 3).astype(np.float64)
    ok = (px < CLIPPED).all(1)
    if ok.mean() < MIN_UNCLIPPED:
        raise ValueError(f"{path}: {1 - ok.mean():.0%} of the patch {x0},{y0},{x1},{y1} is "
                         "clipped (white in some channel): pick a darker reference (a grey "
                         "card) or a less exposed photo")
    rgb = srgb_decode(px[ok]).mean(0)
    if not (rgb > 1e-4).all():
        raise ValueError(f"{path}: the patch {x0},{y0},{x1},{y1} is black in some channel "
                         f"(linear {_fmt(rgb)}): pick a lit, grey reference")
    return {"photo": str(path), "box": [int(x0), int(y0), int(x1), int(y1)],
            "rgb": [float(v) for v in rgb], "pixels": int(ok.sum()),
            "clipped": int((~ok).sum())}


# ----------------------------------------------------------------------------- estimates

def gain_from_reference(object_patch: dict, scene_patch: dict) -> ExposureGain:
    """``g = p_s / p_o`` from one reference surface's mean linear colour in a scene photo and
    in an object photo (:func:`linear_patch`), lit alike in both."""
    po, ps = np.asarray(object_patch["rgb"]), np.asarray(scene_patch["rgb"])
    return ExposureGain(
        tuple(ps / po), "reference",
        "the reference patch has one reflectance and is lit by the same light in the object "
        "photo and in the scene photo, so the ratio of its colours is the ratio of the two "
        "captures' camera gains (exposure × white balance); " + LINEARISED,
        {"object_patch": object_patch, "scene_patch": scene_patch})


def gain_from_grey_world(albedo, weights=None) -> ExposureGain:
    """White balance from the object's albedo [N, 3] (``weights`` [N], e.g. opacities):
    ``g ∝ 1 / m`` for its weighted mean albedo ``m``, so ``g ⊙ m`` is grey, scaled to
    luminance 1 (``Y(g) = 1``: a white balance, no exposure change)."""
    a = np.asarray(albedo, np.float64).reshape(-1, 3)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, np.float64).ravel()
    if len(a) == 0 or w.sum() <= 0:
        raise ValueError("grey-world exposure: the object has no (visible) surfel")
    m = (w[:, None] * a).sum(0) / w.sum()
    if not (m > 1e-4).all():
        raise ValueError(f"grey-world exposure: the object's mean albedo {_fmt(m)} is black "
                         "in some channel; give --exposure-gain or --white-patch instead")
    g = 1.0 / m
    return ExposureGain(
        tuple(g / float(LUMA @ g)), "grey-world",
        "grey world: the object's mean albedo is taken to be grey, so its mean colour is the "
        "object capture's colour cast (white balance only; its luminance, the exposure, is "
        "kept: gain luminance 1). A truly coloured object is wrongly made grey on average",
        {"mean_albedo": [float(v) for v in m], "surfels": int(len(a))})


def resolve_exposure(gain=None, white_patch=None) -> ExposureGain:
    """The exposure of the command-line choices: ``gain`` (R, G, B), ``white_patch``
    (``(object photo spec, scene photo spec)``, :func:`parse_patch`) or neither (gain 1,
    assumed). Grey world needs the object's albedo: ``gain_from_grey_world``."""
    if gain is not None and white_patch is not None:
        raise ValueError("give --exposure-gain or --white-patch, not both")
    if gain is not None:
        return ExposureGain(tuple(gain), "given",
                            "the gain was given (--exposure-gain): scene-capture linear units "
                            "per object-capture unit")
    if white_patch is not None:
        obj, scene = (linear_patch(*parse_patch(s)) for s in white_patch)
        return gain_from_reference(obj, scene)
    return ExposureGain()
