"""Training of the light head (``lighting.lights``): the power of lights clipped at EV 0.

Data: the shared real maps minus ``pano_data.HELD_OUT``, Mitsuba ``sunsky`` skies and
path-traced procedural rooms (``pano_data``), seen through traced surfel masks
(``data.pano_masks``) at several panorama heights (``heights``: the head must serve the
64-px benchmark and the 512-px trace of ``estimate-light``). Each draw rotates, mirrors,
re-exposes (auto exposure × 2^U(−aug_ev, aug_ev)) and white-balances a map, exposes it to an
EV-0 LDR panorama, finds its clipped regions and records each region's features and target
log(P_true / P_seen) (luminance power of the true map over the region vs. that of the LDR
pixels).

Validation is by map identity, never by draw: ``--cv`` (default on) first refits the head
with each real map left out in turn (and with a quarter of the skies, a quarter of the rooms
left out) and records the mean absolute error of the log gain on what was left out, beside a
constant guess (the training median); the shipped head is then fitted on everything.

Loss: Huber (δ = 0.5) on the log gain; AdamW (weight decay ``weight_decay``), minibatches of
512, cosine learning rate; the defaults were chosen by that cross-validation. The shipped
head is ``lighting/weights/light_head.pt``.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from comgs_dr.core.colorspace import LUMA
from comgs_dr.core.config import add_config_arguments, config_overrides, shared_options
from comgs_dr.core.equirect import pixel_solid_angles
from comgs_dr.core.runlog import json_safe
from comgs_dr.core.variant import set_variant
from comgs_dr.data import pano_masks
from comgs_dr.data.synthetic import shared_data_dir
from comgs_dr.lighting import completion as C
from comgs_dr.lighting import lights as L
from comgs_dr.lighting import pano_data as P
from comgs_dr.lighting.hdr import area_resize_equirect

log = logging.getLogger(__name__)


@dataclass
class TrainLightHeadConfig:
    """Settings of :func:`train`.

    out: the head's weights (default ``out/light_head.pt``; the shipped ``L.DEFAULT_HEAD``
        is replaced only when named here), its card beside it as JSON.
    data_dir: folder of the generated regions (``light_head_data.npz``, reused while the
        data settings match).
    maps_dir: folder of real .hdr/.exr maps (None: ``shared/data/hdri``); held_out: the file
        stems of the maps never trained on.
    heights: panorama heights the regions are drawn at, multiples of 64 (default 64, 128,
        256, 512: the head serves small benchmarks and ``estimate-light``'s 512-px trace).
    draws_real: draws per real map and height (default 60).
    n_sky, draws_sky: sunsky skies (the same ones at every height) and draws per sky and
        height (default 240, 3).
    n_rooms, draws_room: path-traced rooms (used at 64 and 128 px only) and draws per room
        and height (default 100, 4).
    room_bulbs: half the rooms with bare bulbs (``pano_data.room_panorama``; default off).
    room_height: height the rooms are traced at, area-averaged below it (default 64).
    white_core: train only on regions with a white core, as ``clipped_regions(white_core=
        True)`` finds them (default off: every clipped region).
    ensemble: > 1: save a ``lights.HeadEnsemble`` of heads fitted with seeds seed … seed +
        ensemble − 1 (the cross-validation folds fit the same ensemble); a single head's
        light directions vary with its seed (default 1).
    scene_probes, draws_scene: per real map, panoramas of its light *inside a scene*,
        path-traced at a random placement in ``make-dataset composition``'s procedural scene
        (ground, wall, box) under the map turned by a random azimuth (:func:`scene_probe`),
        and draws of each at every height; the bare maps never show the ground and walls a
        placement sees (default 0: none; 10 draws).
    n_masks: traced surfel masks the draws are seen through (default 120).
    aug_ev: re-exposure of each draw, auto exposure × 2^U(−aug_ev, aug_ev) (default 1.5).
    wb_jitter: std of the log per-channel white-balance gain (default 0.1).
    full_view: fraction of draws with the whole sphere observed (default 0.15).
    blur_frac, blur_deg: fraction of draws whose LDR panorama is blurred as a
        reconstruction's sky holds it (:func:`blur_ldr`), with σ ~ U(blur_deg) in degrees
        (default 0: none; 0.5–3°).
    steps, lr, hidden, weight_decay: AdamW steps, learning rate, hidden units and weight
        decay of the fit (default 1000, 3e-3, 64, 1e-2; chosen by the cross-validation).
    rank_weight: weight of the listwise ranking term (:func:`_rank_loss`): per panorama, the
        cross-entropy of the softmax of the predicted log powers against that of the true
        ones (the Huber loss scores each region apart; which region is strongest sets the
        light's direction). Default 0: off.
    cv: cross-validate by map identity before the final fit (default on).
    seed, threads: random seed and torch threads (default 0, 2).
    """
    out: Path = Path("out/light_head.pt")
    data_dir: Path = Path("out/light_head_data")
    maps_dir: Path | None = None
    held_out: tuple = P.HELD_OUT
    heights: tuple = (64, 128, 256, 512)
    draws_real: int = 60
    n_sky: int = 240
    draws_sky: int = 3
    n_rooms: int = 100
    draws_room: int = 4
    room_bulbs: bool = False
    room_height: int = 64
    white_core: bool = False
    ensemble: int = 1
    scene_probes: int = 0
    draws_scene: int = 10
    n_masks: int = 120
    aug_ev: float = 1.5
    wb_jitter: float = 0.1
    full_view: float = 0.15
    blur_frac: float = 0.0
    blur_deg: tuple = (0.5, 3.0)
    steps: int = 1000
    rank_weight: float = 0.0
    lr: float = 3e-3
    hidden: int = 64
    weight_decay: float = 1e-2
    cv: bool = True
    seed: int = 0
    threads: int = 2


def _draws(rng, hdr, masks, n, cfg, label, group, feats, targets, groups, panos, seen_log):
    """``n`` augmented views of ``hdr``: per clipped region its features, log gain, group
    (map identity), panorama index (a running count) and log seen power."""
    h, w = hdr.shape[:2]
    dw = np.broadcast_to(pixel_solid_angles(h, w), (h, w))
    k = P.auto_exposure(hdr)
    for _ in range(n):
        m, a, ldr = P.augmented_view(rng, hdr, k, masks, cfg.aug_ev, cfg.wb_jitter,
                                     cfg.full_view)
        if rng.random() < cfg.blur_frac:
            ldr = blur_ldr(ldr, a, rng.uniform(*cfg.blur_deg) * h / 180.0)
        lab = label if rng.random() > 0.2 else C.LABELS["unknown"]
        regions = L.clipped_regions(ldr, a, white_core=cfg.white_core)
        if not regions:
            continue
        feats.append(L.region_features(ldr, a, regions, lab))
        lum = m @ LUMA
        pano = panos[-1] + 1 if panos else 0
        for r in regions:
            true = float((lum * dw * r.pixels).sum())
            seen = max(float(r.seen_power @ LUMA), 1e-12)
            targets.append(np.log(max(true / seen, 1.0)))
            groups.append(group)
            panos.append(pano)
            seen_log.append(np.log(seen))


def scene_probe(env, rng, textures: dict, height: int = 256, spp_side: int = 4) -> np.ndarray:
    """[height, 2·height, 3] light arriving at a random placement (x, y within ±0.3 of the
    centre, 0.15–0.6 above the ground) of the composition scene (``composition_dataset.scene_layout``
    with a random wall azimuth and clearance) lit by the equirect map ``env`` [H, W, 3]
    turned by a random azimuth; ``textures``: ``composition_dataset.write_textures``."""
    from types import SimpleNamespace

    import mitsuba as mi

    from comgs_dr.data import composition_dataset as comp
    from comgs_dr.data.placement_probe import render_probe
    env = np.roll(np.asarray(env, np.float32), int(rng.integers(env.shape[1])), axis=1)
    layout = comp.scene_layout(float(rng.uniform(0.0, 360.0)), float(rng.uniform(0.6, 1.2)))
    cfg = SimpleNamespace(max_depth=comp.CompositionDatasetConfig.max_depth,
                          scene_envmap_scale=1.0, fov_deg=40.0, resolution=8)
    scene = mi.load_dict(comp.scene_dict(cfg, mi.Bitmap(env), textures, layout))
    pos = np.array([*rng.uniform(-0.3, 0.3, 2), rng.uniform(0.15, 0.6)])
    return render_probe(scene, pos, height, spp_side, seed=int(rng.integers(1000)))


def blur_ldr(ldr, alpha, sigma_px: float) -> np.ndarray:
    """The EV-0 LDR panorama as a reconstruction holds it: a sky learned from LDR images at
    the reconstruction's resolution is their clipped display values, averaged, so a sun
    reaches the trace as a soft blob around a white core. Mask-normalised Gaussian (σ in
    pixels, wrapping in u), zero outside the mask."""
    from scipy.ndimage import gaussian_filter
    a = (alpha > 0.5).astype(np.float64)
    mode = ("nearest", "wrap")
    num = np.stack([gaussian_filter(ldr[..., c] * a, sigma_px, mode=mode) for c in range(3)], -1)
    den = gaussian_filter(a, sigma_px, mode=mode)[..., None]
    return np.where(a[..., None] > 0, num / np.maximum(den, 1e-6), 0.0)


def _resize_rows(img, h: int) -> np.ndarray:
    """[h, 2h, 3]: ``img`` [H, 2H, 3] area-averaged (``hdr.area_resize_equirect``: power kept)
    when h ≤ H, pixel-repeated when H divides h."""
    H = img.shape[0]
    if h <= H:
        return area_resize_equirect(img, h, 2 * h)
    if h % H:
        raise ValueError(f"{h} is not a multiple of the room height {H}")
    return np.repeat(np.repeat(img, h // H, 0), h // H, 1)


def build_data(cfg: TrainLightHeadConfig, progress: bool = True) -> dict:
    """Features [N, F], targets [N] (log gain), groups [N] (map identity), panos [N] (which
    panorama), log_seen [N] (log of the region's seen luminance power) and names."""
    cache = Path(cfg.data_dir) / "light_head_data.npz"
    key = json.dumps({k: str(v) for k, v in asdict(cfg).items()
                      if k not in ("out", "steps", "lr", "hidden", "threads", "weight_decay", "cv",
                                   "ensemble", "rank_weight")}
                     | {"features": list(L.FEATURES)}, sort_keys=True)
    if cache.is_file():
        d = dict(np.load(cache, allow_pickle=False))
        if str(d.get("key")) == key and "panos" in d:        # older caches lack panos
            return d
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    mdir = Path(cfg.maps_dir) if cfg.maps_dir else shared_data_dir() / "hdri"
    files = P.map_files(mdir, cfg.held_out)
    masks = np.stack([m["alpha"] for m in pano_masks.mask_bank(
        cfg.n_masks, 64, 128, seed=cfg.seed + 1, progress=progress)]).astype(np.float32)
    rh = cfg.room_height
    rooms = [P.room_panorama(rng, rh, 2 * rh, spp=16, seed=cfg.seed * 7919 + i,
                             bulbs=cfg.room_bulbs)
             for i in tqdm(range(cfg.n_rooms), desc="rooms", disable=not progress)]
    probes = _scene_probes(cfg, files, progress)
    feats, targets, groups, panos, seen_log = _draw_regions(rng, cfg, files, masks, rooms,
                                                            probes, progress)
    d = {"features": np.concatenate(feats).astype(np.float32),
         "targets": np.asarray(targets, np.float32), "groups": np.asarray(groups, np.int64),
         "panos": np.asarray(panos, np.int64), "log_seen": np.asarray(seen_log, np.float32),
         "names": np.array([p.stem for p in files]), "key": np.array(key),
         "seconds": np.array(time.perf_counter() - t0)}
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, **d)
    tmp.replace(cache)
    return d


def _scene_probes(cfg: TrainLightHeadConfig, files: list, progress: bool) -> dict:
    """{real map index: [cfg.scene_probes panoramas of it inside the composition scene, at
    256 rows]} (:func:`scene_probe`); {} when ``cfg.scene_probes`` is 0."""
    probes = {}
    if cfg.scene_probes > 0 and any(h > 256 and h % 256 for h in cfg.heights):
        raise ValueError(f"--scene-probes: the probes are rendered at 256 rows, so --heights "
                         f"must be ≤ 256 or multiples of it, got {list(cfg.heights)}")
    if cfg.scene_probes > 0:
        from comgs_dr.data.composition_dataset import write_textures
        textures = write_textures(Path(cfg.data_dir) / "scene_textures")
        prng = np.random.default_rng(cfg.seed + 31)
        for i, p in enumerate(tqdm(files, desc="scene probes", disable=not progress)):
            env = P.load_map(p, 256, 512)
            probes[i] = [scene_probe(env, prng, textures) for _ in range(cfg.scene_probes)]
    return probes


def _draw_regions(rng, cfg: TrainLightHeadConfig, files: list, masks, rooms: list, probes: dict,
                  progress: bool) -> tuple[list, list, list, list, list]:
    """(features, targets, groups, panos, log_seen) of the clipped regions of every draw
    (:func:`_draws`), at every height: the scene probes, the real maps, the skies (groups
    1000 + i) and, at 128 rows or fewer, the rooms (groups 2000 + i)."""
    feats, targets, groups, panos, seen_log = acc = [], [], [], [], []
    for h in cfg.heights:
        for i, ps in probes.items():
            for pr in ps:
                _draws(rng, _resize_rows(pr, h).astype(np.float64), masks, cfg.draws_scene, cfg,
                       C.LABELS[P.label_of(files[i].stem)], i, *acc)
        for i, p in enumerate(tqdm(files, desc=f"maps {h}px", disable=not progress)):
            _draws(rng, P.load_map(p, h, 2 * h).astype(np.float64), masks, cfg.draws_real,
                   cfg, C.LABELS[P.label_of(p.stem)], i, *acc)
        sky_rng = np.random.default_rng(cfg.seed + 99)          # the same skies at every size
        for i in tqdm(range(cfg.n_sky), desc=f"skies {h}px", disable=not progress):
            sky = P.sunsky_panorama(sky_rng, h, 2 * h).astype(np.float64)
            _draws(rng, sky, masks, cfg.draws_sky, cfg, C.LABELS["outdoor"],
                   1000 + i, *acc)
        if h <= 128:
            for i, room in enumerate(rooms):
                room = _resize_rows(room, h).astype(np.float64)
                if room.max() > 0:
                    _draws(rng, room, masks, cfg.draws_room, cfg, C.LABELS["indoor"],
                           2000 + i, *acc)
    return feats, targets, groups, panos, seen_log


def _huber(pred, tgt, delta: float = 0.5):
    return torch.nn.functional.huber_loss(pred, tgt, delta=delta)


def _rank_loss(pred, y, log_seen, seg):
    """Listwise ranking loss: mean over panoramas of −Σ softmax(t) · log softmax(s), with
    s = log seen + pred, t = log seen + y (natural-log powers) over each panorama's regions;
    ``seg`` [n] the panorama of each region, 0 … B − 1. The segmented log-softmax is written
    with ``scatter_reduce`` / ``index_add``: torch has none built in (torch_scatter is not a
    dependency); ``tests/test_lights.py`` checks it against a per-panorama loop."""
    s, t = log_seen + pred, log_seen + y                              # [n]
    b = int(seg.max()) + 1

    def log_softmax(v):
        m = v.new_full((b,), -torch.inf).scatter_reduce(0, seg, v.detach(), "amax")
        e = v.new_zeros(b).index_add(0, seg, torch.exp(v - m[seg]))
        return v - m[seg] - torch.log(e)[seg]
    p = torch.exp(log_softmax(t))
    return -(p * log_softmax(s)).sum() / b


class _PanoSampler:
    """Random batches of whole panoramas with ≥ 2 regions (their region indices and a
    0 … B − 1 panorama index per region)."""

    def __init__(self, panos: np.ndarray, seed: int):
        order = np.argsort(panos, kind="stable")
        _, start, count = np.unique(panos[order], return_index=True, return_counts=True)
        keep = count >= 2
        self.order, self.start, self.count = order, start[keep], count[keep]
        self.rng = np.random.default_rng(seed)

    def __bool__(self):
        return len(self.start) > 0

    def sample(self, k: int = 64):
        pick = self.rng.integers(len(self.start), size=min(k, len(self.start)))
        idx = np.concatenate([self.order[s:s + c] for s, c in
                              zip(self.start[pick], self.count[pick])])
        seg = np.repeat(np.arange(len(pick)), self.count[pick])
        return torch.from_numpy(idx), torch.from_numpy(seg)


def fit_head(x: torch.Tensor, y: torch.Tensor, cfg: TrainLightHeadConfig,
             hist: list | None = None, panos: np.ndarray | None = None,
             log_seen: torch.Tensor | None = None) -> L.LightHead:
    """A LightHead fitted to features x [N, F] and log gains y [N] (standardised inputs);
    with ``cfg.rank_weight`` > 0 also the ranking loss over ``panos`` [N] (panorama of each
    region) and ``log_seen`` [N]."""
    if cfg.rank_weight > 0 and (panos is None or log_seen is None):
        raise ValueError("fit_head: rank_weight > 0 needs each region's panorama and seen power")
    ranker = _PanoSampler(panos, cfg.seed + 2) if cfg.rank_weight > 0 else None
    torch.manual_seed(cfg.seed)
    head = L.LightHead(x.shape[1], cfg.hidden)
    head.mean.copy_(x.mean(0))
    head.std.copy_(x.std(0, correction=0).clamp_min(1e-3))     # finite for one region
    opt = torch.optim.AdamW(head.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    rng = np.random.default_rng(cfg.seed + 1)
    t0 = time.perf_counter()
    for step in range(cfg.steps):
        for gr in opt.param_groups:
            gr["lr"] = cfg.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * step / cfg.steps)))
        idx = torch.from_numpy(rng.integers(len(x), size=min(512, len(x))))
        loss = _huber(head(x[idx]), y[idx])
        if ranker:
            ri, seg = ranker.sample()
            loss = loss + cfg.rank_weight * _rank_loss(head(x[ri]), y[ri], log_seen[ri], seg)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if hist is not None and ((step + 1) % 250 == 0 or step == 0):
            with torch.no_grad():
                hist.append({"step": step + 1, "time_s": round(time.perf_counter() - t0, 2),
                             "train_huber": round(float(_huber(head(x), y)), 4),
                             "train_mae_log": round(float((head(x) - y).abs().mean()), 4)})
    return head.eval()


def fit_heads(x: torch.Tensor, y: torch.Tensor, cfg: TrainLightHeadConfig,
              hist: list | None = None, panos=None, log_seen=None
              ) -> L.LightHead | L.HeadEnsemble:
    """``fit_head`` with seed ``cfg.seed``, or with ``cfg.ensemble`` > 1 a ``HeadEnsemble``
    of heads fitted with seeds seed … seed + ensemble − 1 (``hist``: the first's curve)."""
    head = fit_head(x, y, cfg, hist, panos, log_seen)
    if cfg.ensemble <= 1:
        return head
    return L.HeadEnsemble([head] + [fit_head(x, y, replace(cfg, seed=cfg.seed + k), None,
                                             panos, log_seen)
                                    for k in range(1, cfg.ensemble)])


def top1(score: np.ndarray, truth: np.ndarray, panos: np.ndarray) -> tuple[float, int]:
    """Fraction of panoramas with ≥ 2 regions whose highest ``score`` is the region of
    highest ``truth`` (per-region log powers), and how many such panoramas there are."""
    order = np.lexsort((-score, panos))
    first_pred = order[np.r_[True, panos[order][1:] != panos[order][:-1]]]
    order = np.lexsort((-truth, panos))
    first_true = order[np.r_[True, panos[order][1:] != panos[order][:-1]]]
    _, count = np.unique(panos, return_counts=True)
    multi = count >= 2
    if not multi.any():
        return float("nan"), 0
    return float(np.mean(first_pred[multi] == first_true[multi])), int(multi.sum())


def cross_validate(x, y, groups, names, cfg: TrainLightHeadConfig,
                   save_dir: Path | None = None, panos: np.ndarray | None = None,
                   log_seen: torch.Tensor | None = None) -> list[dict]:
    """Leave-one-real-map-out, and quarter-of-skies / quarter-of-rooms-out folds: the mean
    absolute error of the log gain on the left-out regions, and a constant guess's (with
    ``panos`` and ``log_seen``: also ``top1``, how often the predicted strongest region of a
    left-out panorama is the true one, and ``top1_seen`` by seen power alone). Each
    fold fits what ``train`` ships (``fit_heads``: an ensemble when ``cfg.ensemble`` > 1).
    ``save_dir``: each left-out map's fold head is saved there as ``<map stem>.pt`` with its
    card (``maps``: the real maps it was fitted on), for ``lighting_eval --cv-heads``: a
    head that never saw the map it is scored on."""
    folds = [(str(n), groups == i) for i, n in enumerate(names)]
    for base, kind in ((1000, "skies"), (2000, "rooms")):
        sel = (groups >= base) & (groups < base + 1000)
        if sel.any():
            folds.append((f"{kind} (1/4)", sel & ((groups - base) % 4 == 0)))
    out = []
    for name, te in folds:
        te = torch.from_numpy(te)
        if not te.any() or te.all():
            continue
        sel = te.numpy()                                   # the left-out regions, numpy
        head = fit_heads(x[~te], y[~te], cfg, None, panos[~sel] if panos is not None else None,
                         log_seen[~te] if log_seen is not None else None)
        with torch.no_grad():
            pred = head(x[te])
        err = pred - y[te]
        out.append({"left_out": name, "regions": int(te.sum()),
                    "mae_log": round(float(err.abs().mean()), 3),
                    "bias_log": round(float(err.mean()), 3),
                    "mae_log_const": round(float((y[te] - y[~te].median()).abs().mean()), 3)})
        if panos is not None and log_seen is not None:
            ls, pt = log_seen[te].numpy(), panos[sel]
            out[-1]["top1"], out[-1]["panoramas"] = top1(ls + pred.numpy(),
                                                         ls + y[te].numpy(), pt)
            out[-1]["top1_seen"] = top1(ls, ls + y[te].numpy(), pt)[0]
            for k in ("top1", "top1_seen"):
                out[-1][k] = round(out[-1][k], 3)
        if save_dir is not None and name in set(map(str, names)):
            fold = {"left_out": name, "maps": [str(n) for n in names if str(n) != name],
                    "held_out": list(cfg.held_out) + [name], "cross_validation": [out[-1]],
                    "config": {k: (str(v) if isinstance(v, Path) else v)
                               for k, v in asdict(cfg).items()}}
            path = Path(save_dir) / f"{name}.pt"
            L.save_head(head, path, fold)
            path.with_suffix(".json").write_text(json.dumps(json_safe(fold), indent=1,
                                                            allow_nan=False))
    return out


def train(cfg: TrainLightHeadConfig, progress: bool = True, command: str = "",
          cv_dir: Path | None = None) -> dict:
    """Build (or load) the data, cross-validate (fold heads saved in ``cv_dir`` when given),
    fit the head on everything and save it with its card at ``cfg.out``."""
    torch.set_num_threads(cfg.threads)
    data = build_data(cfg, progress)
    x = torch.from_numpy(data["features"])
    y = torch.from_numpy(data["targets"])
    t0 = time.perf_counter()
    panos, log_seen = data["panos"], torch.from_numpy(data["log_seen"])
    cv = (cross_validate(x, y, data["groups"], data["names"], cfg, cv_dir, panos, log_seen)
          if cfg.cv else [])
    hist = []
    head = fit_heads(x, y, cfg, hist, panos, log_seen)
    info = {"command": command, "regions": int(len(y)),
            "data_seconds": float(data["seconds"]),
            "train_seconds": round(time.perf_counter() - t0, 1),
            "maps": [str(n) for n in data["names"]], "held_out": list(cfg.held_out),
            "cross_validation": cv,
            "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
            "history": hist}
    L.save_head(head, cfg.out, info)
    Path(cfg.out).with_suffix(".json").write_text(json.dumps(json_safe(info), indent=1,
                                                             allow_nan=False))
    return info


#: ``--out`` (``core.config.shared_options``) of ``comgs train-light-head``.
OUT_OPTION = dict(type=Path, default=None, metavar="HEAD.pt",
                  help=f"weights (default {TrainLightHeadConfig.out}; the shipped ones, "
                       f"{L.DEFAULT_HEAD}, are replaced only when named here; use yours with "
                       f"estimate-light --light-head)")


def add_arguments(ap) -> None:
    """The ``comgs train-light-head`` flags (also ``python -m
    comgs_dr.stages.train_light_head``): every scalar field of :class:`TrainLightHeadConfig`
    as ``--field-name`` (``core.config.add_config_arguments``), some also under the name
    users typed before (``--skies`` for ``n_sky``); ``--out`` and ``--quiet`` where ``ap``
    lacks them (a parser not built on ``core.config.shared_options``)."""
    if not any(a.dest == "out" for a in ap._actions):
        ap.add_argument("--out", **OUT_OPTION)
        ap.add_argument("--quiet", action="store_true", help="no progress bars")
    # older spellings, switches, paths and lists (add_config_arguments makes plain typed flags)
    ap.add_argument("--draws", "--draws-real", dest="draws_real", type=int, default=None,
                    help="draws per real map and size")
    ap.add_argument("--skies", "--n-sky", dest="n_sky", type=int, default=None)
    ap.add_argument("--rooms", "--n-rooms", dest="n_rooms", type=int, default=None)
    ap.add_argument("--masks", "--n-masks", dest="n_masks", type=int, default=None)
    ap.add_argument("--bulbs", dest="room_bulbs", action="store_const", const=True, default=None,
                    help="half the rooms with bare bulbs")
    ap.add_argument("--white-core", action="store_const", const=True, default=None,
                    help="train only on regions with a white core (as inference sees them; "
                         "the shipped head saw every clipped one)")
    ap.add_argument("--no-cv", dest="cv", action="store_const", const=False, default=None,
                    help="skip the cross-validation")
    ap.add_argument("--data-dir", type=Path, default=None)
    ap.add_argument("--maps", dest="maps_dir", type=Path, default=None,
                    help="folder of .hdr/.exr maps")
    ap.add_argument("--held-out", nargs="*", default=None, metavar="NAME")
    ap.add_argument("--heights", type=int, nargs="+", default=None)
    # not a config field: where train() saves the cross-validation's fold heads
    ap.add_argument("--cv-out", type=Path, default=None, help="save each left-out map's "
                    "cross-validation head here as <map stem>.pt (for lighting_eval --cv-heads)")
    add_config_arguments(ap, TrainLightHeadConfig)


def config_from_args(args) -> TrainLightHeadConfig:
    """The config of the flags ``args`` holds (what was not typed keeps its default);
    ValueError for an ensemble below 1 or a height that is no multiple of 64."""
    kw = {k: tuple(v) if isinstance(v, list) else v
          for k, v in config_overrides(args, TrainLightHeadConfig).items()}
    cfg = TrainLightHeadConfig(**kw)
    if cfg.ensemble < 1:
        raise ValueError(f"--ensemble must be >= 1, got {cfg.ensemble}")
    if any(h < 16 or h % 64 for h in cfg.heights):
        raise ValueError(f"--heights must be multiples of 64, got {list(cfg.heights)}")
    return cfg


def run_from_args(args) -> int:
    cfg = config_from_args(args)
    if args.cv_out is not None and not cfg.cv:
        raise ValueError("--cv-out saves the cross-validation's heads; it cannot go with --no-cv")
    info = train(cfg, progress=not args.quiet, command=" ".join(sys.argv), cv_dir=args.cv_out)
    print(f"saved {cfg.out}: {info['regions']} regions, training MAE of log gain "
          f"{info['history'][-1]['train_mae_log']}")
    if info["cross_validation"]:
        print("| left out | regions | MAE log gain | bias | constant guess | panoramas | "
              "strongest first | by seen power |\n|---|---|---|---|---|---|---|---|")
        for r in info["cross_validation"]:
            print(f"| {r['left_out']} | {r['regions']} | {r['mae_log']} | {r['bias_log']} | "
                  f"{r['mae_log_const']} | {r.get('panoramas', '')} | {r.get('top1', '')} | "
                  f"{r.get('top1_seen', '')} |")
    return 0


if __name__ == "__main__":
    set_variant("llvm_ad_rgb")
    _ap = argparse.ArgumentParser(prog="comgs train-light-head", description=__doc__,
                                  formatter_class=argparse.RawDescriptionHelpFormatter,
                                  parents=[shared_options(out=OUT_OPTION, mitsuba_variant=False)])
    add_arguments(_ap)
    sys.exit(run_from_args(_ap.parse_args()))
