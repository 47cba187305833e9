"""Indoor / outdoor from the observed panorama: the label the completion net, its SH blend and
the light head are conditioned on, when the user does not give it (``label="auto"``).

Why: the models estimate the light clearly better with the true label than with "unknown"
(the dominant light's direction most of all), and a user who runs ``estimate-light``
without ``--label`` would otherwise get "unknown".

The classifier: L2-regularised, sample-weighted logistic regression on ``FEATURES``, global
statistics of the observed EV-0 LDR panorama by elevation band, exposure-free but for
clipping (brightness of the upper bands relative to the whole, their blueness relative to
the lower band, chroma, clipping, texture, and how much of them is seen). A linear model on
a handful of physical cues rather than a network: it is trained on 8 real maps plus
procedural skies and rooms (``stages.train_scene_label``) and must not learn the maps. Where it is unsure
(p(outdoor) within ``margin`` of ½) it answers "unknown", which is what the models were
trained to handle without a label.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from comgs_dr.core.colorspace import LUMA, srgb_decode
from comgs_dr.core.equirect import pixel_solid_angles
from comgs_dr.core.runlog import json_safe
from comgs_dr.lighting.hdr import SAT, area_resize_equirect, check_ldr_mask

__all__ = ["FEATURES", "label_features", "LabelModel", "fit_logistic", "load_model",
           "save_model", "classify", "resolve_label", "LABEL_CHOICES", "DEFAULT_MODEL", "SAT"]

ROWS = 32                  # features are read at this height (texture at a fixed scale)
LABEL_CHOICES = ("auto", "outdoor", "indoor", "unknown")   # "auto": ``classify``
DEFAULT_MODEL = Path(__file__).parent / "weights" / "scene_label.json"
_FORMAT = "comgs_dr.lighting.scene_label/1"
_BANDS = {"top": (40.0, 90.0), "up": (10.0, 40.0), "low": (-90.0, -10.0)}   # elevation, °

FEATURES = ("rel_top", "rel_up", "rel_low", "blue_up_minus_low", "blue_top_minus_up",
            "sat_top", "clip_up", "tex_up", "tex_low", "seen_up", "seen_top")


def _check(ldr, mask):
    ldr, seen = check_ldr_mask(ldr, mask, "scene_label")
    if ldr.shape[0] < 2 or ldr.shape[1] < 2:
        raise ValueError(f"scene_label: need an equirect panorama of at least 2×2, got "
                         f"{ldr.shape}")
    return ldr, seen.astype(np.float64)


def _small(ldr, seen, rows: int):
    """(linear rgb [r, 2r, 3], clipped fraction, observed fraction), r = min(H, rows),
    area-averaged over the observed pixels only (a hole does not darken its neighbours)."""
    r = min(ldr.shape[0], rows)
    lin = srgb_decode(ldr)
    clip = (ldr.max(-1) >= SAT).astype(np.float64)
    if ldr.shape[:2] == (r, 2 * r):
        return lin * seen[..., None], clip * seen, seen
    stack = np.concatenate([lin * seen[..., None], (clip * seen)[..., None], seen[..., None]], -1)
    s = area_resize_equirect(stack, r, 2 * r)
    a = s[..., 4]
    inv = np.where(a > 1e-6, 1.0 / np.maximum(a, 1e-6), 0.0)
    return s[..., :3] * inv[..., None], s[..., 3] * inv, a


def label_features(ldr, mask) -> np.ndarray:
    """[len(FEATURES)] float64 statistics of the observed EV-0 LDR panorama ``ldr`` [H, W, 3]
    (display values, equirect; mask [H, W], 1 = observed), read at ``ROWS`` × 2·``ROWS``. Brightness features are logs of band
    means over the whole observed mean (exposure-free); colour is a difference of band
    blueness (white-balance-free to first order). A band with nothing observed gives 0 for
    its relative features (``seen_*`` says so)."""
    ldr, seen = _check(ldr, mask)
    lin, clip, a = _small(ldr, seen, ROWS)
    h, w = a.shape
    el = 90.0 - (np.arange(h) + 0.5) * 180.0 / h                                     # [h]
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w)) * a                     # [h, w]
    lum = lin @ LUMA
    tot = float(dw.sum())
    if tot <= 0:
        raise ValueError("scene_label: nothing of the panorama is observed")
    mean_all = float((lum * dw).sum() / tot)

    def band(name):
        lo, hi = _BANDS[name]
        return ((el >= lo) & (el < hi))[:, None] & (a > 1e-6)

    def rel(sel):
        wgt = float((dw * sel).sum())
        if wgt <= 1e-9:
            return 0.0
        return float(np.log((lum * dw * sel).sum() / wgt + 1e-3) - np.log(mean_all + 1e-3))

    def blue(sel):
        rgb = (lin * (dw * sel)[..., None]).sum((0, 1))
        return float(rgb[2] / rgb.sum()) if rgb.sum() > 1e-9 else 1.0 / 3.0

    def sat(sel):
        """Mean chroma (max − min over max of linear rgb) inside ``sel``, solid-angle weighted."""
        mx, mn = lin.max(-1), lin.min(-1)
        c = np.where(mx > 1e-6, (mx - mn) / np.maximum(mx, 1e-6), 0.0)
        wgt = float((dw * sel).sum())
        return float((c * dw * sel).sum() / wgt) if wgt > 1e-9 else 0.0

    def tex(sel):
        """Mean |Δ log lum| between neighbours (right and below) inside ``sel``, both more
        than half observed (a ragged mask edge does not count as texture)."""
        sel = sel & (a > 0.5)
        ll = np.log(lum + 1e-3)
        dx = np.abs(ll - np.roll(ll, -1, 1))
        ok_x = sel & np.roll(sel, -1, 1)
        dy = np.abs(ll[:-1] - ll[1:])
        ok_y = sel[:-1] & sel[1:]
        n = ok_x.sum() + ok_y.sum()
        return float((dx[ok_x].sum() + dy[ok_y].sum()) / n) if n else 0.0

    up_geo = (el > 0)[:, None]
    area_up = float((np.broadcast_to(pixel_solid_angles(h, w), (h, w)) * up_geo).sum())
    area_top = float((np.broadcast_to(pixel_solid_angles(h, w), (h, w))
                      * (el >= 40.0)[:, None]).sum())
    up, top, low = band("up") | band("top"), band("top"), band("low")
    seen_up = float((dw * up_geo).sum()) / area_up
    clip_up = float((clip * dw * up_geo).sum() / max((dw * up_geo).sum(), 1e-12))
    return np.array([rel(top), rel(band("up")), rel(low), blue(up) - blue(low),
                     blue(top) - blue(band("up")), sat(top), clip_up,
                     tex(up), tex(low), seen_up, float((dw * top).sum()) / area_top])


@dataclass
class LabelModel:
    """Logistic regression p(outdoor) = σ(coef · (x − mean) / std + bias)."""
    mean: list
    std: list
    coef: list
    bias: float
    margin: float = 0.2              # |p − ½| below it: "unknown"
    features: tuple = FEATURES
    info: dict | None = None

    def p_outdoor(self, x) -> np.ndarray:
        """[N] p(outdoor) of features x [N, F] (or [F])."""
        x = np.atleast_2d(np.asarray(x, np.float64))
        z = ((x - np.asarray(self.mean)) / np.asarray(self.std)) @ np.asarray(self.coef)
        return 1.0 / (1.0 + np.exp(-np.clip(z + self.bias, -50.0, 50.0)))

    def decide(self, p: float) -> str:
        if p >= 0.5 + self.margin:
            return "outdoor"
        if p <= 0.5 - self.margin:
            return "indoor"
        return "unknown"


def fit_logistic(x, y, l2: float = 1.0, margin: float = 0.2, w=None) -> LabelModel:
    """LabelModel fitted to features x [N, F], y [N] (1 = outdoor) and sample weights w [N]
    (None: 1) by Newton's method on the weighted mean log loss + (l2 / 2N)·|coef|²
    (standardised features; the bias is not penalised). Hand-written (a dozen lines):
    scikit-learn is not a dependency."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    w = np.ones(len(y)) if w is None else np.asarray(w, np.float64)
    if x.ndim != 2 or len(x) != len(y) or len(w) != len(y) or len(x) < 2:
        raise ValueError(f"fit_logistic: need x [N, F], y [N], w [N], N ≥ 2, got {x.shape}, "
                         f"{y.shape}, {w.shape}")
    if not ((y == 0) | (y == 1)).all() or y.min() == y.max():
        raise ValueError("fit_logistic: y must hold both classes, as 0 / 1")
    if not (np.isfinite(w).all() and (w >= 0).all() and w.sum() > 0) or not l2 > 0:
        raise ValueError("fit_logistic: weights must be finite, ≥ 0, not all 0; l2 > 0")
    w = w / w.mean()                                                                # [N]
    mean = (w[:, None] * x).sum(0) / w.sum()                                        # [F]
    std = np.maximum(np.sqrt((w[:, None] * (x - mean) ** 2).sum(0) / w.sum()), 1e-6)
    z = np.concatenate([(x - mean) / std, np.ones((len(x), 1))], 1)                # [N, F+1]
    n, f = z.shape
    reg = np.full(f, l2 / n)
    reg[-1] = 0.0
    beta = np.zeros(f)
    for _ in range(100):
        p = 1.0 / (1.0 + np.exp(-np.clip(z @ beta, -50, 50)))
        g = z.T @ (w * (p - y)) / n + reg * beta
        hess = (z * (w * p * (1 - p))[:, None]).T @ z / n + np.diag(reg) + 1e-9 * np.eye(f)
        step = np.linalg.solve(hess, g)
        beta -= step
        if np.abs(step).max() < 1e-10:
            break
    else:
        raise ValueError("fit_logistic: Newton's method did not converge in 100 steps "
                         "(separable data? raise l2)")
    return LabelModel(mean.tolist(), std.tolist(), beta[:-1].tolist(), float(beta[-1]), margin)


def save_model(model: LabelModel, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    d = asdict(model)
    nums = np.array([*model.mean, *model.std, *model.coef, model.bias], np.float64)
    if not np.isfinite(nums).all():
        raise ValueError(f"save_model: the model has non-finite parameters; not written to {path}")
    d["features"] = list(model.features)
    path.write_text(json.dumps(json_safe({"format": _FORMAT, **d}), indent=1, allow_nan=False))
    return path


def load_model(path=DEFAULT_MODEL) -> LabelModel:
    """LabelModel from ``save_model``; FileNotFoundError if missing, ValueError for another
    format or feature list."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene-label model not found: {path}")
    try:
        d = json.loads(path.read_text())
    except ValueError as exc:
        raise ValueError(f"{path}: not a readable scene-label model ({exc})") from exc
    if not isinstance(d, dict) or d.pop("format", None) != _FORMAT:
        raise ValueError(f"{path}: not a scene-label model (format {_FORMAT!r} expected)")
    if tuple(d.get("features", ())) != FEATURES:
        raise ValueError(f"{path}: made for other features; retrain with "
                         f"comgs train-scene-label --out {path}")
    d["features"] = FEATURES
    return LabelModel(**d)


_CACHE: dict = {}


def classify(ldr, mask, model: LabelModel | str | Path | None = None) -> tuple[str, float]:
    """("indoor" | "outdoor" | "unknown", p(outdoor)) of an observed EV-0 panorama; ``model``
    None: the shipped one (loaded once)."""
    if model is None or isinstance(model, (str, Path)):
        key = str(DEFAULT_MODEL if model is None else model)
        if key not in _CACHE:
            _CACHE[key] = load_model(key)
        model = _CACHE[key]
    p = float(model.p_outdoor(label_features(ldr, mask))[0])
    return model.decide(p), p


def resolve_label(label: str, ldr, mask, model=None) -> tuple[str, float | None]:
    """(label for the models, p(outdoor) or None): ``label`` itself unless it is "auto",
    then ``classify``'s answer. ValueError for a label outside ``LABEL_CHOICES``."""
    if label not in LABEL_CHOICES:
        raise ValueError(f"label must be one of {LABEL_CHOICES}, got {label!r}")
    if label != "auto":
        return label, None
    return classify(ldr, mask, model)
