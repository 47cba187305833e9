"""Training of the indoor / outdoor classifier (``lighting.scene_label``), ``label="auto"``.

Data: the shared real maps minus ``pano_data.HELD_OUT`` (labels from ``pano_data.label_of``),
Mitsuba ``sunsky`` skies (outdoor) and path-traced procedural rooms (indoor), each drawn
several times as the completion sees them: rotated, mirrored, re-exposed (auto exposure ×
2^U(−aug_ev, aug_ev)), white-balanced, exposed to an EV-0 LDR panorama and masked by traced
surfel masks (``data.pano_masks``; a fraction fully observed). Classes are weighted equally
and each real map weighs as much as all skies (or all rooms) together.

Validation is by map identity: each real map is left out in turn (the model refitted on the
rest) and its draws scored; then the held-out maps (never used in fitting) are scored by
the model fitted on everything. Reported: accuracy of the hard decision, the fraction
answered "unknown", and the wrong answers.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from comgs_dr.core.config import add_config_arguments, config_overrides, shared_options
from comgs_dr.core.variant import set_variant
from comgs_dr.data import pano_masks
from comgs_dr.data.synthetic import shared_data_dir
from comgs_dr.lighting import pano_data as P
from comgs_dr.lighting import scene_label as S

OUTDOOR, INDOOR = 1, 0


@dataclass
class TrainSceneLabelConfig:
    """Settings of :func:`train`.

    out: the model (default ``out/scene_label.json``; the shipped ``S.DEFAULT_MODEL`` is
        replaced only when named here).
    maps_dir: folder of real .hdr/.exr maps (None: ``shared/data/hdri``); held_out: the file
        stems of the maps never fitted on (scored at the end).
    heights: panorama heights the real maps are drawn at (default 64, 256).
    draws_real: draws per real map and height (default 40).
    n_sky, n_rooms: sunsky skies and path-traced rooms (default 150 each), ``draws_synth``
        draws of each (default 2); rooms traced at ``room_spp`` samples per pixel (default
        16), the share ``finished_rooms`` in [0, 1] drawn finished (``pano_data.
        _finish_room``: white ceiling, wood floor, strip lights; default 0).
    n_masks: traced surfel masks the draws are seen through (default 60).
    aug_ev: re-exposure of each draw, auto exposure × 2^U(−aug_ev, aug_ev) (default 1.5).
    wb_jitter: std of the log per-channel white-balance gain (default 0.1).
    full_view: fraction of draws with the whole sphere observed (default 0.1).
    l2, margin: the logistic fit's L2 weight (> 0; default 1) and the margin around
        p = 0.5 answered "unknown" (in [0, 0.5); default 0.2).
    seed: random seed (default 0).
    """
    out: Path = Path("out/scene_label.json")
    maps_dir: Path | None = None
    held_out: tuple = P.HELD_OUT
    heights: tuple = (64, 256)
    draws_real: int = 40
    n_sky: int = 150
    n_rooms: int = 150
    finished_rooms: float = 0.0
    room_spp: int = 16
    draws_synth: int = 2
    n_masks: int = 60
    aug_ev: float = 1.5
    wb_jitter: float = 0.1
    full_view: float = 0.1
    l2: float = 1.0
    margin: float = 0.2
    seed: int = 0

    def __post_init__(self):
        if not 0.0 <= float(self.finished_rooms) <= 1.0 or int(self.room_spp) < 1:
            raise ValueError(f"TrainSceneLabelConfig: finished_rooms must lie in [0, 1] and "
                             f"room_spp be >= 1, got {self.finished_rooms}, {self.room_spp}")


def _draw(rng, hdr, masks, cfg) -> np.ndarray:
    """Features of one augmented, exposed, masked draw of an HDR panorama [h, w, 3]."""
    _, a, ldr = P.augmented_view(rng, hdr, P.auto_exposure(hdr), masks, cfg.aug_ev,
                                 cfg.wb_jitter, cfg.full_view)
    return S.label_features(ldr, a)


def build_data(cfg: TrainSceneLabelConfig, progress: bool = True) -> dict:
    """x [N, F], y [N] (1 outdoor), weight [N], group [N] (real map index; −1 sky, −2 room),
    held-out x / y / group, names of the training and held-out maps."""
    rng = np.random.default_rng(cfg.seed)
    mdir = Path(cfg.maps_dir) if cfg.maps_dir else shared_data_dir() / "hdri"
    files = P.map_files(mdir)
    masks = [m["alpha"] for m in pano_masks.mask_bank(cfg.n_masks, 64, 128, seed=cfg.seed + 1,
                                                       progress=progress)]
    train = [p for p in files if p.stem not in cfg.held_out]
    held = [p for p in files if p.stem in cfg.held_out]
    if not train:
        raise FileNotFoundError(f"train-scene-label: no training maps in {mdir}")
    rows = {"train": ([], [], []), "held": ([], [], [])}
    for split, group in (("train", train), ("held", held)):
        for i, p in enumerate(tqdm(group, desc=f"{split} maps", disable=not progress)):
            y = OUTDOOR if P.label_of(p.stem) == "outdoor" else INDOOR
            for h in cfg.heights:
                hdr = P.load_map(p, h, 2 * h).astype(np.float64)
                for _ in range(cfg.draws_real):
                    rows[split][0].append(_draw(rng, hdr, masks, cfg))
                    rows[split][1].append(y)
                    rows[split][2].append(i)
    xs, ys, gs = rows["train"]
    for _ in tqdm(range(cfg.n_sky), desc="skies", disable=not progress):
        sky = P.sunsky_panorama(rng, 64, 128).astype(np.float64)
        for _ in range(cfg.draws_synth):
            xs.append(_draw(rng, sky, masks, cfg)), ys.append(OUTDOOR), gs.append(-1)
    for i in tqdm(range(cfg.n_rooms), desc="rooms", disable=not progress):
        room = P.room_panorama(rng, 64, 128, spp=cfg.room_spp, seed=cfg.seed * 7919 + i,
                               finished=bool(rng.random() < cfg.finished_rooms)
                               if cfg.finished_rooms > 0 else False).astype(np.float64)
        if room.max() <= 0:
            continue
        for _ in range(cfg.draws_synth):
            xs.append(_draw(rng, room, masks, cfg)), ys.append(INDOOR), gs.append(-2)
    x, y, g = np.asarray(xs), np.asarray(ys, np.float64), np.asarray(gs)
    return {"x": x, "y": y, "group": g, "weight": sample_weights(y, g),
            "held_x": np.asarray(rows["held"][0]).reshape(-1, len(S.FEATURES)),
            "held_y": np.asarray(rows["held"][1], np.float64),
            "held_group": np.asarray(rows["held"][2]),
            "names": [p.stem for p in train], "held_names": [p.stem for p in held]}


def sample_weights(y, group) -> np.ndarray:
    """Each real map weighs as much as all skies or all rooms; then both classes weigh the
    same. Mean 1."""
    w = np.zeros(len(y))
    for gr in np.unique(group):
        sel = group == gr
        w[sel] = 1.0 / sel.sum()
    for c in (0, 1):
        sel = y == c
        if sel.any():
            w[sel] *= 0.5 / w[sel].sum()
    return w * len(y)


def fit(x, y, w, cfg: TrainSceneLabelConfig) -> S.LabelModel:
    """The classifier fitted to x [N, F], y [N] with sample weights w [N]."""
    return S.fit_logistic(x, y, cfg.l2, cfg.margin, w)


def score(model: S.LabelModel, x, y) -> dict:
    """Hard decisions of ``model`` on x [N, F] against y [N]: correct / unknown / wrong."""
    p = model.p_outdoor(x)
    dec = np.array([model.decide(v) for v in p])
    truth = np.where(y > 0.5, "outdoor", "indoor")
    known = dec != "unknown"
    return {"draws": int(len(y)), "correct": int((dec == truth).sum()),
            "unknown": int((~known).sum()), "wrong": int((known & (dec != truth)).sum()),
            "mean_p_outdoor": round(float(p.mean()), 3)}


def cross_validate(d: dict, cfg: TrainSceneLabelConfig) -> list[dict]:
    """Each real training map left out in turn: refit (weights rebalanced) and score it."""
    out = []
    for i, name in enumerate(d["names"]):
        te = d["group"] == i
        w = sample_weights(d["y"][~te], d["group"][~te])      # balanced without the map
        m = fit(d["x"][~te], d["y"][~te], w, cfg)
        out.append({"left_out": name, **score(m, d["x"][te], d["y"][te])})
    return out


def train(cfg: TrainSceneLabelConfig, progress: bool = True, command: str = "") -> dict:
    t0 = time.perf_counter()
    d = build_data(cfg, progress)
    t_data = time.perf_counter() - t0
    cv = cross_validate(d, cfg)
    model = fit(d["x"], d["y"], d["weight"], cfg)
    held = [{"map": n, **score(model, d["held_x"][d["held_group"] == i],
                               d["held_y"][d["held_group"] == i])}
            for i, n in enumerate(d["held_names"])]
    model.info = {"command": command, "draws": int(len(d["y"])), "maps": d["names"],
                  "held_out": list(cfg.held_out), "data_seconds": round(t_data, 1),
                  "cross_validation": cv, "held_out_scores": held,
                  "train_scores": score(model, d["x"], d["y"]),
                  "config": {k: (str(v) if isinstance(v, Path) else v)
                             for k, v in asdict(cfg).items()}}
    S.save_model(model, cfg.out)
    return model.info


#: ``--out`` (``core.config.shared_options``) of ``comgs train-scene-label``.
OUT_OPTION = dict(type=Path, default=None, metavar="MODEL.json",
                  help=f"model (default {TrainSceneLabelConfig.out}; the shipped one, "
                       f"{S.DEFAULT_MODEL}, is replaced only when named here; use yours with "
                       f"estimate-light / compose --scene-label)")


def add_arguments(ap) -> None:
    """The ``comgs train-scene-label`` flags (also ``python -m
    comgs_dr.stages.train_scene_label``): every scalar field of
    :class:`TrainSceneLabelConfig` as ``--field-name`` (``core.config.add_config_arguments``),
    some also under the name users typed before (``--skies`` for ``n_sky``); ``--out`` and
    ``--quiet`` where ``ap`` lacks them (a parser not built on
    ``core.config.shared_options``)."""
    if not any(a.dest == "out" for a in ap._actions):
        ap.add_argument("--out", **OUT_OPTION)
        ap.add_argument("--quiet", action="store_true", help="no progress bars")
    # older spellings, paths and lists (add_config_arguments makes plain typed flags)
    ap.add_argument("--draws", "--draws-real", dest="draws_real", type=int, default=None,
                    help="draws per real map and size")
    ap.add_argument("--skies", "--n-sky", dest="n_sky", type=int, default=None)
    ap.add_argument("--rooms", "--n-rooms", dest="n_rooms", type=int, default=None)
    ap.add_argument("--maps", dest="maps_dir", type=Path, default=None,
                    help="folder of .hdr/.exr maps")
    ap.add_argument("--held-out", nargs="*", default=None, metavar="NAME")
    add_config_arguments(ap, TrainSceneLabelConfig)


def config_from_args(args) -> TrainSceneLabelConfig:
    """The config of the flags ``args`` holds (what was not typed keeps its default);
    ValueError naming the flag of a value out of range."""
    kw = {k: tuple(v) if isinstance(v, list) else v
          for k, v in config_overrides(args, TrainSceneLabelConfig).items()}
    d = TrainSceneLabelConfig()
    v = {k: kw.get(k, getattr(d, k)) for k in ("margin", "draws_real", "n_sky", "n_rooms", "l2",
                                              "finished_rooms", "room_spp")}
    if not 0.0 <= v["margin"] < 0.5:
        raise ValueError(f"--margin must lie in [0, 0.5), got {v['margin']}")
    if v["draws_real"] < 1 or v["n_sky"] < 0 or v["n_rooms"] < 0 or not v["l2"] > 0:
        raise ValueError("--draws must be >= 1; --skies, --rooms >= 0; --l2 > 0")
    if not 0.0 <= v["finished_rooms"] <= 1.0 or v["room_spp"] < 1:
        raise ValueError(f"--finished-rooms must lie in [0, 1] and --room-spp be >= 1, got "
                         f"{v['finished_rooms']}, {v['room_spp']}")
    return TrainSceneLabelConfig(**kw)


def run_from_args(args) -> int:
    cfg = config_from_args(args)
    info = train(cfg, progress=not args.quiet, command=" ".join(sys.argv))
    print(f"saved {cfg.out}: {info['draws']} draws; on them {info['train_scores']}")
    print("| left out / held out | draws | correct | unknown | wrong | mean p(outdoor) |\n"
          "|---|---|---|---|---|---|")
    for r in info["cross_validation"] + info["held_out_scores"]:
        name = r.get("left_out") or f"{r['map']} (held out)"
        print(f"| {name} | {r['draws']} | {r['correct']} | {r['unknown']} | {r['wrong']} | "
              f"{r['mean_p_outdoor']} |")
    return 0


if __name__ == "__main__":
    set_variant("llvm_ad_rgb")
    _ap = argparse.ArgumentParser(prog="comgs train-scene-label", description=__doc__,
                                  formatter_class=argparse.RawDescriptionHelpFormatter,
                                  parents=[shared_options(out=OUT_OPTION, mitsuba_variant=False)])
    add_arguments(_ap)
    sys.exit(run_from_args(_ap.parse_args()))
