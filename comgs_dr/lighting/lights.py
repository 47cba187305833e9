"""Dominant lights as spherical-Gaussian lobes, and a learned head for the power of clipped ones.

Paper, Appendix "Details of Lighting Estimation": strong lights are extracted after the fact
(luminance > mean + 5σ) and re-added to the completed map. With LDR captures that re-adds a
*clipped* light: a sun seen at EV 0 is stored at the white level, 10³–10⁵× below its radiance,
and the EV −2.5/−5 completions can bring back at most 32× (``hdr.saturation_limit``). Composited
objects then get washed-out shading and weak shadows. This module adds what the brackets
cannot:

* **Lobes** (``lighting.sg``: ``sg_integral``, ``sg_sharpness``, ``render_lobes``): an SG
  L(ω) = a·exp(λ(ω·μ − 1)) with ∫ = a·2π/λ·(1 − e^{−2λ}); ``render_lobes`` draws lobes into
  an equirect map with their exact power Σ L dω (normalised on the pixel grid, so a lobe
  narrower than a pixel keeps its power).
* **Clipped regions** (``clipped_regions``, in ``light_regions``): connected components (``hdr.label_equirect``:
  seam and poles merged) of observed EV-0 pixels whose max channel is ≥ ``sat``, largest
  observed power first.
* **Features** (``region_features``, ``FEATURES``): scale-free descriptors of a region and of
  the observed panorama around it (its solid angle, elevation, how fully it is clipped, the
  brightness, colour and clipping of rings around it, the label, the image resolution)
  and its EV-0 power against the panorama's other regions (``light_regions``).
* **The head** (``LightHead``): a small MLP from the features to log(P_true / P_seen), the
  ratio of the region's true luminance power to what the EV-0 pixels hold, ≥ 0 (softplus:
  clipping only removes light). Trained by ``comgs train-light-head`` on the training maps'
  true powers (``stages.train_light_head``). An MLP on hand-made features, not a CNN: the
  quantity is one number per region, the training set is a few thousand regions, and it must
  generalise from 8 real maps plus procedural skies.
* ``add_lights``: the fused HDR map with, per clipped region, the predicted power: where the
  completion's EV < 0 brackets already put more there, their excess over the EV-0 white
  level is scaled down to it (``excess="match"``: otherwise a window the net made brighter
  than the head's prediction outshines the lamps the head restored); where it holds less,
  the *missing* power (predicted power − the fused map's power there) is added, coloured
  like the unclipped ring around the region (the sun's glow; white where no ring pixel is seen),
  drawn inside the region's pixels with weights ∝ (fused luminance) × the region's SG lobe
  (centred on the region, the region's solid angle): a bare SG lobe would spill the ring
  colour outside the region, and the region without the lobe makes a wide clipped sky
  patch read as a weak, flat light. The lobes' parameters are returned (``env.json``).
* **The brackets' vote** (``shared_power``, ``add_lights(trust_brackets=¼)``): the head sets
  the total clipped power, and each region's share ∝ P_head^¾ · P_brackets^¼. Which of
  several white lamps is strongest is what the head ranks worst, hardly better than their
  EV-0 power; the net's EV < 0 brackets carry other evidence, and the mix ranks best.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.equirect import equirect_directions, pixel_solid_angles
from comgs_dr.lighting.hdr import SAT
from comgs_dr.lighting.light_regions import (BANDS_DEG, FEATURES, MAX_REGIONS, N_BASE_FEATURES,
                                             Region, _check, _unit, clipped_regions,
                                             region_features, ring_colour)
from comgs_dr.lighting.sg import render_lobes, sg_integral, sg_sharpness
from comgs_dr.lighting.torch_io import load_torch_file

__all__ = ["sg_integral", "sg_sharpness", "render_lobes", "Region", "clipped_regions",
           "FEATURES", "N_BASE_FEATURES", "region_features", "ring_colour", "BANDS_DEG",
           "MAX_REGIONS", "LightHead", "HeadEnsemble", "save_head", "load_head",
           "DEFAULT_HEAD", "predict_lobes", "downsample_clipped",
           "shared_power", "vote_shares", "add_lights", "describe_regions", "regions_overlay",
           "SAT", "TRUST_BRACKETS"]

MAX_LOG_GAIN = 25.0       # P_true / P_seen ≤ e^25 ≈ 7e10 (a real sun at EV 0: ~1e5)
TRUST_BRACKETS = 0.25      # add_lights: the brackets' vote on which region holds the power
DEFAULT_HEAD = Path(__file__).parent / "weights" / "light_head.pt"
_FORMAT = "comgs_dr.lighting.light_head/1"


# ---- The head ----

class LightHead(nn.Module):
    """MLP: standardised features [B, F] -> log gain [B] ≥ 0 (softplus). ``FEATURES`` only
    grows at its end: a head fitted on the first n features reads those (``n_features``)."""

    def __init__(self, n_features: int = len(FEATURES), hidden: int = 64):
        super().__init__()
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("std", torch.ones(n_features))
        self.mlp = nn.Sequential(nn.Linear(n_features, hidden), nn.SiLU(),
                                 nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, 1))
        self.hidden = hidden

    @property
    def n_features(self) -> int:
        return len(self.mean)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x[..., :self.n_features]
        return nn.functional.softplus(self.mlp((x - self.mean) / self.std)[..., 0])


class HeadEnsemble(nn.Module):
    """The mean log gain of LightHeads fitted with different seeds (``fit_head``)."""

    def __init__(self, heads: list[LightHead]):
        super().__init__()
        if not heads:
            raise ValueError("HeadEnsemble: need at least one head")
        self.heads = nn.ModuleList(heads)
        self.hidden = heads[0].hidden

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([h(x) for h in self.heads]).mean(0)


def _cpu_state(head: LightHead) -> dict:
    return {k: v.detach().cpu() for k, v in head.state_dict().items()}


def save_head(head: LightHead | HeadEnsemble, path, info: dict | None = None) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    members = list(head.heads) if isinstance(head, HeadEnsemble) else [head]
    n = (head.heads[0] if isinstance(head, HeadEnsemble) else head).n_features
    torch.save({"format": _FORMAT, "features": list(FEATURES[:n]), "hidden": head.hidden,
                "state_dict": _cpu_state(members[0]),
                "members": [_cpu_state(h) for h in members[1:]], "info": info or {}}, path)
    return path


def load_head(path=DEFAULT_HEAD) -> LightHead | HeadEnsemble:
    """LightHead, or HeadEnsemble when the file holds several, (eval mode) from ``save_head``
    ("default": ``DEFAULT_HEAD``); FileNotFoundError if
    missing, ValueError for another format or another feature list."""
    path = DEFAULT_HEAD if str(path) == "default" else Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"light head weights not found: {path}")
    ck = load_torch_file(path, _FORMAT, "light-head file")
    feats = ck.get("features")
    if not isinstance(feats, list) or not feats or feats != list(FEATURES[:len(feats)]):
        raise ValueError(f"{path}: made for other features; retrain with comgs "
                         f"train-light-head --out {path}")
    heads = []
    for sd in [ck["state_dict"], *ck.get("members", [])]:
        heads.append(LightHead(len(feats), int(ck["hidden"])))
        heads[-1].load_state_dict(sd)
    return (heads[0] if len(heads) == 1 else HeadEnsemble(heads)).eval()


@torch.no_grad()
def predict_lobes(ldr, mask, head: LightHead, label: int = 2, sat: float = SAT,
                  max_regions: int = MAX_REGIONS) -> list[dict]:
    """Lobes of the clipped regions of the EV-0 panorama: ``direction``, ``solid_angle``,
    ``sharpness``, ``gain`` (predicted P_true / P_seen), ``luminance_power`` (predicted),
    ``colour`` (ring chromaticity) and ``region`` ([H, W] bool)."""
    regions = clipped_regions(ldr, mask, sat, max_regions)
    if not regions:
        return []
    x = torch.from_numpy(region_features(ldr, mask, regions, label, sat))
    gain = np.exp(np.clip(np.nan_to_num(head(x).numpy().astype(np.float64)), 0.0, MAX_LOG_GAIN))
    out = []
    for r, g in zip(regions, gain):
        om = min(r.solid_angle, 4 * np.pi * 0.999)
        out.append({"direction": r.direction, "solid_angle": r.solid_angle,
                    "sharpness": float(sg_sharpness(om)), "gain": float(g),
                    "luminance_power": float(g * (r.seen_power @ LUMA)),
                    "colour": ring_colour(ldr, mask, r, sat), "region": r.pixels})
    return out


def downsample_clipped(ldr, mask, f: int, sat: float = SAT, fraction: float = 0.75):
    """(ldr [H/f, W/f, 3], mask [H/f, W/f]) of an EV-0 panorama in f×f blocks: the block
    mean, except that a block whose observed clipped pixels (max channel ≥ ``sat``) make up
    ≥ ``fraction`` of it takes its brightest clipped pixel (largest channel sum) and counts
    as observed, as a coarser capture's pixel over a light would be clipped. For running the
    head at the resolution at which clipping is known (``estimate_light.head_factor``).

    ``fraction``: a low one dilates scattered patches of bright sky into one large false
    light, a full block (1) loses the edge of a real sun; ¾ keeps the sun and not the
    patches. A light of one full-size pixel is averaged away at ¾ (such a panorama comes
    from a capture that saw it coarser anyway).
    ValueError if f does not divide H and W."""
    ldr, seen = _check(ldr, mask)
    f = int(f)
    h, w = seen.shape
    if f < 1 or h % f or w % f:
        raise ValueError(f"downsample_clipped: factor {f} must be >= 1 and divide {h}x{w}")
    if f == 1:
        return ldr, seen.astype(np.float64)
    hb, wb = h // f, w // f
    blk = ldr.reshape(hb, f, wb, f, 3).transpose(0, 2, 1, 3, 4).reshape(hb, wb, f * f, 3)
    sb = seen.reshape(hb, f, wb, f).transpose(0, 2, 1, 3).reshape(hb, wb, f * f)
    clip = sb & (blk.max(-1) >= sat)                                       # [hb, wb, f²]
    score = np.where(clip, blk.sum(-1), -1.0)
    pick = np.take_along_axis(blk, score.argmax(-1)[..., None, None], 2)[:, :, 0]
    has = (clip.mean(-1) >= fraction) & clip.any(-1)
    out = np.where(has[..., None], pick, blk.mean(2))
    m = np.where(has, 1.0, sb.mean(-1))
    return out, m


def _match_excess(out, reg, lum, dw, target: float) -> float:
    """Scale, inside ``reg``, the part of ``out`` above the EV-0 white level (1 per channel:
    what the completion's EV < 0 brackets added to the clipped pixels) so the region's
    luminance power falls to ``target``; never below the white level. ``out`` and its
    luminance ``lum`` are updated in place; returns the region's power afterwards."""
    have = float((lum * dw * reg).sum())
    floor = np.minimum(out[reg], 1.0)                                         # [P, 3]
    base = float(((floor @ LUMA) * dw[reg]).sum())
    if have <= target or have <= base:
        return have
    k = max(target - base, 0.0) / (have - base)
    out[reg] = floor + k * (out[reg] - floor)
    lum[reg] = out[reg] @ LUMA
    return max(target, base)


def shared_power(lobes, lum, dw, a: float) -> np.ndarray:
    """[R] the lobes' luminance powers after ``add_lights``' ``trust_brackets`` = a:
    Σ P_pred · w / Σ w, w = P_pred^(1−a) · P_map^a (P_map: ``lum`` [H, W] · ``dw`` summed over
    the region; regions are disjoint). a = 0 or one lobe: P_pred unchanged. The exponent
    1 − a also compresses the head's range: a sun of gain 33 beside a sky patch of gain 2
    (brackets 1.9× and 1.5× their EV-0 power) keeps 92 % and the patch gets 1.75×. With a
    fill backend P_map is the EV-0 power, so the vote leans to the larger clipped region.
    ValueError unless 0 ≤ a ≤ 1."""
    pred = np.array([float(lb["luminance_power"]) for lb in lobes])           # [R]
    if float(a) <= 0 or len(lobes) < 2:
        return vote_shares(pred, pred, a)                 # validates a; pred unchanged
    have = np.array([float((lum * dw * np.asarray(lb["region"], bool)).sum()) for lb in lobes])
    return vote_shares(pred, have, a)


def vote_shares(pred, have, a: float) -> np.ndarray:
    """[R] Σ pred · w / Σ w, w = pred^(1−a) · have^a: the arithmetic of ``shared_power`` on
    given powers. ValueError unless
    0 ≤ a ≤ 1."""
    a_in, a = a, float(a)
    if not 0.0 <= a <= 1.0:
        raise ValueError(f"trust_brackets must lie in [0, 1], got {a_in!r}")
    pred = np.asarray(pred, np.float64)
    if a <= 0 or len(pred) < 2:
        return pred
    w = np.maximum(pred, 1e-30) ** (1.0 - a) * np.maximum(have, 1e-30) ** a
    return pred.sum() * w / w.sum()


def add_lights(hdr_map, lobes, shape: str = "sg_region", sharpen: float = 1.0,
               excess: str = "match", trust_brackets: float = TRUST_BRACKETS
               ) -> tuple[np.ndarray, list[dict]]:
    """The fused map [H, W, 3] plus each lobe's missing power: P − (the map's luminance power
    inside the lobe's region), ≥ 0, coloured by the lobe's ``colour``; P is the lobe's share
    of the head's power after the brackets' vote (``shared_power``; P_pred when a = 0).

    ``excess``: where the map already holds more than P inside the region (a completion
    net's EV −2.5/−5 brackets re-predict clipped pixels), ``"match"`` scales that excess over
    the EV-0 white level down to P (the head's power is the region's power: a window the net
    made too bright would otherwise outshine the lamps the head restored); ``"keep"``
    leaves it (the map's light is never removed). The missing power is drawn as

    * ``shape="sg"``: an SG at the region's centroid with the region's solid angle;
    * ``shape="region"``: inside the region's pixels, with weights ∝ (the fused map's
      luminance)^``sharpen`` (where the completion put more light; uniform for a fill);
    * ``shape="sg_region"``: inside the region's pixels, weights of "region" × the SG.

    ``trust_brackets`` a ∈ [0, 1]: the head's total power Σ P_pred is shared among the
    regions in proportion to P_pred^(1−a) · P_map^a, P_map the map's own power in the region
    (the completion's EV < 0 brackets): the head sets how much clipped light there is, the
    brackets also vote on which region holds it. 0: the head alone. (The brackets' absolute
    power is not used: it cannot exceed 32× the white level, so a lone sun keeps the head's
    power.)

    Returns (map, the lobes as added: direction, sharpness, solid_angle, rgb_power,
    amplitude, gain; for "region" the direction and sharpness are those of the drawn power)."""
    if shape not in ("sg", "region", "sg_region"):
        raise ValueError(f"add_lights: shape must be 'sg', 'region' or 'sg_region', got "
                         f"{shape!r}")
    if excess not in ("match", "keep"):
        raise ValueError(f"add_lights: excess must be 'match' or 'keep', got {excess!r}")
    img = np.asarray(hdr_map, np.float64)
    if img.ndim != 3 or img.shape[-1] != 3 or not np.isfinite(img).all():
        raise ValueError(f"add_lights: need a finite [H, W, 3] map, got {img.shape}")
    h, w = img.shape[:2]
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    lum = img @ LUMA
    out = img.copy()
    added, sg_lobes = [], []
    targets = shared_power(lobes, lum, dw, trust_brackets)                    # [R]
    for lb, target in zip(lobes, targets):
        reg = np.asarray(lb["region"], bool)
        if excess == "match":
            have = _match_excess(out, reg, lum, dw, target)
        else:
            have = float((lum * dw * reg).sum())
        missing = max(target - have, 0.0)
        if missing <= 0:
            continue
        rgb = missing * np.asarray(lb["colour"], np.float64)
        direction, sharp = np.asarray(lb["direction"], np.float64), float(lb["sharpness"])
        if shape != "sg":
            wgt = np.where(reg, np.maximum(lum, 1e-12) ** float(sharpen), 0.0)
            if shape == "sg_region":
                wgt = wgt * np.exp(sharp * (equirect_directions(h, w) @ direction - 1.0))
            wgt = wgt / float((wgt * dw).sum())                               # Σ w dω = 1
            out += wgt[..., None] * rgb
            direction = _unit((equirect_directions(h, w) * (wgt * dw)[..., None]).sum((0, 1)))
        else:
            sg_lobes.append({"direction": direction, "sharpness": sharp, "rgb_power": rgb})
        amp = rgb / float(sg_integral(sharp))
        added.append({"direction": direction, "sharpness": sharp,
                      "solid_angle": lb["solid_angle"], "rgb_power": rgb, "amplitude": amp,
                      "gain": lb.get("gain")})
    return out + render_lobes(sg_lobes, h, w), added


def describe_regions(pred: list[dict], before, after,
                     trust_brackets: float = TRUST_BRACKETS) -> list[dict]:
    """What the light head did to each clipped region it read (``lights.predict_lobes``):
    direction, ``region`` ([H, W] bool), solid angle, predicted gain and luminance power,
    ``voted_power`` (its share of the head's total after the brackets' vote, ``shared_power``
    with ``trust_brackets`` as given to ``add_lights``), the fused brackets' power in the
    region ``before`` it and the map's power ``after`` it, and
    ``action``: "added" (the missing power was drawn), "reduced" (the brackets' excess was
    matched down to the voted share) or "unchanged". ``add_lights`` returns only the added
    lobes; this lists every region, so a light the head weakened is not silently missing
    from ``estimate-light``'s JSON. The action is read from the powers before and after
    (relative tolerance 1e-6), which holds for ``add_lights``' default ``shape="sg_region"``
    (power drawn inside the region); with ``shape="sg"`` a lobe spills outside it."""
    h, w = before.shape[:2]
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    lb_, la_ = np.asarray(before, np.float64) @ LUMA, np.asarray(after, np.float64) @ LUMA
    voted = shared_power(pred, lb_, dw, trust_brackets)                       # [R]
    out = []
    for lb, v in zip(pred, voted):
        reg = np.asarray(lb["region"], bool)
        p0, p1 = float((lb_ * dw * reg).sum()), float((la_ * dw * reg).sum())
        tol = 1e-6 * max(p0, p1, 1e-30)
        out.append({"direction": np.asarray(lb["direction"], np.float64), "region": reg,
                    "solid_angle": float(lb["solid_angle"]), "gain": float(lb["gain"]),
                    "predicted_power": float(lb["luminance_power"]), "voted_power": float(v),
                    "brackets_power": p0, "power": p1,
                    "action": "added" if p1 > p0 + tol else
                              "reduced" if p1 < p0 - tol else "unchanged"})
    return out


DOMINANCE_MARGIN = 1.5     # below it, which clipped light dominates is a near tie


def dominance(regions: list[dict]) -> float | None:
    """Power of the strongest observed clipped region over the next (``describe_regions``'
    "power": the map's after the head), or None with fewer than two regions or a second of
    zero power. It says nothing of lights the completion put in the hole. Below
    ``DOMINANCE_MARGIN`` the dominant direction, and so a composited object's shadow, flips
    with a small power error; above it the ranking can still be wrong."""
    p = sorted((float(g["power"]) for g in regions), reverse=True)
    if len(p) < 2 or not p[1] > 0:
        return None
    return p[0] / p[1]


ACTION_RGB = {"added": (1.0, 0.55, 0.0), "reduced": (0.0, 0.8, 1.0), "unchanged": (0.6, 0.6, 0.6)}


def regions_overlay(rgb, regions) -> np.ndarray:
    """[H, W, 3] the EV-0 panorama ``rgb`` at ⅓ brightness with each region of
    ``describe_regions`` painted in its action's colour (``ACTION_RGB``: orange added, cyan
    reduced, grey unchanged), for ``estimate-light``'s preview."""
    img = np.asarray(rgb, np.float64) / 3.0
    for g in regions:
        img[np.asarray(g["region"], bool)] = ACTION_RGB[g["action"]]
    return img
