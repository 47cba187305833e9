"""Training of the panorama completion network (Appendix "Training Details", on a CPU budget).

Two steps as in the paper, with our small U-Net (``lighting.completion``) instead of SD 2.1:

* **Step 1, LDR completion.** Input: the EV-0 LDR panorama ``clip(srgb(k·2**e_aug·hdr))``
  (k = ``pano_data.auto_exposure``, e_aug ~ U[−aug_ev, aug_ev], the EV shift augmentation)
  masked by a traced mask, with that mask's normals; target: the same exposure, complete.
  No EV conditioning (ev = 0). Random rotation about +Z and mirror in u.
* **Step 2, EV-conditioned.** Same input; the target is the map at a second, random
  relative exposure EV_gt ∈ [EV_min, 0] (half of the draws at {0, −2.5, −5}) and the network is
  conditioned on ξ_ev. The paper's pair construction (I_aug at EV_aug, I_gt at EV_gt).

Loss: L1 between the network's completed output (``completion.blend_observed``: observed pixels
pasted, channels clipped at EV 0 re-predicted at EV < 0, never below the clip) and the target, per-pixel solid-angle weights, divided per sample by
(mean target + 0.02) so dark EV −5 targets weigh as much as EV 0 ones (the paper uses a plain
L1 on a v-prediction; with a direct regressor and dark targets the raw L1 ignores the lights).
AdamW (β = 0.9, 0.999, weight decay 0.01), linear warm-up then cosine decay, gradient
clipping 1.0. The learning rate is 1e-3, not the paper's 1e-4: we train from scratch; its
cosine decay follows the fraction of the time budget spent. Block-averaged L1 terms
(``lowfreq``) weigh the low frequencies that light diffuse and rough objects.

Faults: a checkpoint (``<out stem>.ckpt.pt``: model, AdamW, step, training seconds, the
history and the RNG states) is written atomically every ``checkpoint_every`` steps or
``checkpoint_every_s`` seconds and on SIGINT/SIGTERM; the same command resumes from it (the
budget and step limit may change, the rest of the config may not), continuing the same
random streams, so a resumed run repeats the uninterrupted one.

Data (``pano_data``): Poly Haven maps from ``shared/data/hdri`` minus the held-out ones,
Mitsuba ``sunsky`` skies, path-traced procedural rooms and masks traced from procedural surfel
scenes; generated once into ``DATA_DIR/completion_data.npz`` and reused.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from comgs_dr.core import colorspace, equirect, runlog
from comgs_dr.core.config import add_config_arguments, config_overrides, shared_options
from comgs_dr.core.variant import set_variant
from comgs_dr.data import pano_masks
from comgs_dr.data.synthetic import shared_data_dir
from comgs_dr.lighting import completion as C
from comgs_dr.lighting import pano_data as P
from comgs_dr.lighting.backends import DEFAULT_WEIGHTS
from comgs_dr.lighting.hdr import expose
from comgs_dr.train import checkpoint as ck
from comgs_dr.train.interrupt import CheckpointClock, stop_signals

log = logging.getLogger(__name__)

HELD_OUT = P.HELD_OUT


@dataclass
class TrainCompletionConfig:
    """Settings of :func:`train`.

    out: the weights file (default ``out/completion.pt``; the shipped
        ``backends.DEFAULT_WEIGHTS`` are replaced only when named here); beside it
        ``<stem>.json`` (the model card), ``<stem>.ckpt.pt`` (the checkpoint), the metrics log.
    data_dir: folder of the generated training set (``completion_data.npz``, reused while
        the data settings match).
    maps_dir: folder of real .hdr/.exr maps (None: ``shared/data/hdri`` beside the
        checkout); held_out: the file stems of the maps never trained on.
    height, width: panorama size in pixels, 2:1, height a multiple of 16 (default 64 × 128).
    n_sky, n_rooms, n_masks: sunsky skies, path-traced rooms (``room_spp`` samples per
        pixel) and traced surfel masks generated (default 300, 150, 400; 64 spp).
    minutes: time budget of the training (default 45); max_steps: step limit (100000).
    step1_frac: fraction of the budget spent on EV-0 completion before the EV-conditioned
        step (default 0.55).
    batch, lr, warmup: batch size, peak learning rate and its linear warm-up in steps
        (default 8, 1e-3, 200).
    aug_ev: the EV shift augmentation, e_aug ~ U[−aug_ev, aug_ev] (default 1.5).
    wb_jitter: std of the log per-channel white-balance gain (default 0.1).
    init: weights to start from (fine-tuning; None: from scratch).
    lowfreq: weight of each block-averaged (low-frequency) L1 term of ``completion_loss``
        (default 0.5).
    base_channels: width of the U-Net's first level (default 24).
    prior: "none" (default: the network predicts the panorama, as the shipped weights do)
        or "push_pull" (a residual on the push-pull fill).
    seed, threads: random seed and torch threads (default 0, 2).
    source_probs: probabilities of drawing a Poly Haven map, a sky, a room (default 0.3,
        0.35, 0.35).
    net: more ``completion.CompletionConfig`` fields.
    checkpoint_every, checkpoint_every_s: checkpoint every this many steps and seconds of
        wall time (default 200 and 300; also on SIGINT/SIGTERM).
    """
    out: Path = Path("out/completion.pt")
    data_dir: Path = Path("out/completion_data")
    maps_dir: Path | None = None
    held_out: tuple = HELD_OUT
    height: int = 64
    width: int = 128
    n_sky: int = 300
    n_rooms: int = 150
    n_masks: int = 400
    room_spp: int = 64
    minutes: float = 45.0
    max_steps: int = 100000
    step1_frac: float = 0.55
    batch: int = 8
    lr: float = 1e-3
    warmup: int = 200
    aug_ev: float = 1.5
    wb_jitter: float = 0.1
    init: Path | None = None
    lowfreq: float = 0.5
    base_channels: int = 24
    prior: str = "none"
    seed: int = 0
    threads: int = 2
    source_probs: tuple = (0.3, 0.35, 0.35)
    net: dict = field(default_factory=dict)
    checkpoint_every: int = 200
    checkpoint_every_s: float | None = 300.0

    @property
    def checkpoint_path(self) -> Path:
        return Path(self.out).with_suffix(".ckpt.pt")


# fields a resumed run may change (the rest must match the checkpoint's)
RESUMABLE = ("minutes", "max_steps", "threads", "checkpoint_every", "checkpoint_every_s", "out")


def _config_key(cfg: TrainCompletionConfig) -> dict:
    return {k: (str(v) if isinstance(v, Path) else list(v) if isinstance(v, tuple) else v)
            for k, v in asdict(cfg).items() if k not in RESUMABLE}


def _save_checkpoint(cfg, model, opt, sampler, step, elapsed, hist, step1_end) -> None:
    import io
    buf = io.BytesIO()
    torch.save({"format": "comgs_dr.completion_train/1", "config": _config_key(cfg),
                "model": model.state_dict(), "opt": opt.state_dict(), "step": step,
                "elapsed": elapsed, "hist": hist, "step1_end": step1_end,
                "rng": sampler.rng.bit_generator.state, "torch_rng": torch.get_rng_state()}, buf)
    ck.atomic_write_bytes(cfg.checkpoint_path, buf.getvalue())


def _load_checkpoint(cfg) -> dict | None:
    """The checkpoint of this config, None if there is none; ValueError naming the file if it
    is unreadable or of another config."""
    p = cfg.checkpoint_path
    ck.remove_stale_temporaries(p)
    if not p.is_file():
        return None
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any decoding failure means a bad file
        raise ValueError(f"checkpoint {p} is unreadable ({C.torch_load_error(e)}); delete it "
                         f"to start over") from e
    if not isinstance(state, dict) or state.get("format") != "comgs_dr.completion_train/1":
        raise ValueError(f"checkpoint {p} is not a train-completion checkpoint")
    mine = _config_key(cfg)
    diff = sorted(k for k in set(mine) | set(state["config"])
                  if mine.get(k) != state["config"].get(k))
    if diff:
        raise ValueError(f"checkpoint {p} was made with other settings ({', '.join(diff)}); "
                         "use them, another --out, or delete it to start over")
    return state


def build_data(cfg: TrainCompletionConfig, progress: bool = True) -> dict:
    """Generate (or load the cached) training set: maps [N, H, W, 3], labels [N], source [N]
    (0 Poly Haven, 1 sky, 2 room), masks [M, H, W], normals [M, H, W, 3]."""
    cache = Path(cfg.data_dir) / "completion_data.npz"
    key = f"{cfg.height}x{cfg.width}:{cfg.n_sky}:{cfg.n_rooms}:{cfg.n_masks}:{cfg.seed}:" \
          f"{sorted(cfg.held_out)}:{cfg.room_spp}:{P.GENERATOR_VERSION}"
    if cache.is_file():
        d = dict(np.load(cache, allow_pickle=False))
        if str(d.get("key")) == key:
            return d
        log.info("data cache %s was made with other settings; regenerating", cache)

    rng = np.random.default_rng(cfg.seed)
    h, w = cfg.height, cfg.width
    maps, labels, source, names = [], [], [], []
    mdir = Path(cfg.maps_dir) if cfg.maps_dir else shared_data_dir() / "hdri"
    for p in P.map_files(mdir, cfg.held_out):
        maps.append(P.load_map(p, h, w)), labels.append(C.LABELS[P.label_of(p.stem)])
        source.append(0), names.append(p.stem)
    if not maps:
        log.warning("no Poly Haven maps found in %s: training on procedural data only", mdir)
    for _ in tqdm(range(cfg.n_sky), desc="skies", disable=not progress):
        maps.append(P.sunsky_panorama(rng, h, w)), labels.append(C.LABELS["outdoor"])
        source.append(1), names.append("sunsky")
    for i in tqdm(range(cfg.n_rooms), desc="rooms", disable=not progress):
        maps.append(P.room_panorama(rng, h, w, spp=cfg.room_spp, seed=cfg.seed * 100003 + i))
        labels.append(C.LABELS["indoor"]), source.append(2), names.append("room")
    masks = pano_masks.mask_bank(cfg.n_masks, h, w, seed=cfg.seed + 1, progress=progress)
    d = {"maps": np.stack(maps).astype(np.float32), "labels": np.array(labels, np.int64),
         "source": np.array(source, np.int64), "names": np.array(names),
         "masks": np.stack([m["alpha"] for m in masks]).astype(np.float32),
         "normals": np.stack([m["normal"] for m in masks]).astype(np.float16),
         "coverage": np.array([m["coverage"] for m in masks], np.float32), "key": np.array(key)}
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, **d)
    tmp.replace(cache)
    return d


class Sampler:
    """Random training batches (torch tensors) from ``build_data`` output."""

    def __init__(self, data: dict, cfg: TrainCompletionConfig, seed: int):
        lit = (data["maps"] @ colorspace.LUMA.astype(np.float32)).max((1, 2)) > 0
        if not lit.all():
            log.warning("dropping %d black panoramas from the training set", int((~lit).sum()))
            data = {**data, **{k: data[k][lit] for k in ("maps", "labels", "source", "names")}}
        self.d, self.cfg = data, cfg
        self.rng = np.random.default_rng(seed)
        self.k = np.array([P.auto_exposure(m) for m in data["maps"]])
        src = data["source"]
        p = np.array([cfg.source_probs[s] for s in src], np.float64)
        for s in range(3):   # renormalise so each source gets its share whatever its count
            if (src == s).any():
                p[src == s] /= (src == s).sum()
        self.p = p / p.sum()

    def batch(self, n: int, ev_mode: str):
        rng, d = self.rng, self.d
        H, W = d["maps"].shape[1:3]
        idx = rng.choice(len(d["maps"]), n, p=self.p)
        midx = rng.integers(len(d["masks"]), size=n)
        rgb, tgt, nor, msk, evs, lab = [], [], [], [], [], []
        for i, j in zip(idx, midx):
            hdr = P.rotate_u(d["maps"][i], rng.integers(W))
            if rng.random() < 0.5:
                hdr = hdr[:, ::-1]
            hdr = hdr * self.k[i] * 2.0 ** rng.uniform(-self.cfg.aug_ev, self.cfg.aug_ev)
            if self.cfg.wb_jitter > 0:   # white balance: per-channel gain, luminance kept
                g = np.exp(rng.normal(0.0, self.cfg.wb_jitter, 3))
                hdr = hdr * (g / float(g @ colorspace.LUMA)).astype(np.float32)
            sh = rng.integers(W)
            a = P.rotate_u(d["masks"][j], sh)
            nn = P.rotate_u(d["normals"][j].astype(np.float32), sh)
            if ev_mode == "zero":
                ev = 0.0
            elif rng.random() < 0.5:
                ev = float(rng.choice(C.DEFAULT_EVS))
            else:
                ev = float(rng.uniform(C.EV_MIN, 0.0))
            ldr0 = expose(hdr, 0.0)
            rgb.append(np.where(a[..., None] > 0, ldr0, 0.0)), tgt.append(expose(hdr, ev)), nor.append(nn)
            msk.append(a), evs.append(ev)
            lab.append(d["labels"][i] if rng.random() > 0.2 else C.LABELS["unknown"])

        def t(x):
            return torch.from_numpy(np.ascontiguousarray(np.stack(x), dtype=np.float32))
        return (t(rgb).permute(0, 3, 1, 2), t(nor).permute(0, 3, 1, 2), t(msk)[:, None],
                t(tgt).permute(0, 3, 1, 2), torch.tensor(evs, dtype=torch.float32),
                torch.tensor(lab, dtype=torch.long))


def completion_loss(completed, target, h: int, w: int, lowfreq: float = 0.0,
                    pools: tuple = (4, 16)) -> torch.Tensor:
    """Solid-angle-weighted L1, normalised per sample by (mean target + 0.02).

    ``lowfreq`` > 0 adds, for each factor in ``pools``, ``lowfreq`` × the same L1 between
    solid-angle area averages over pool × pool pixel blocks: the low frequencies that light a
    diffuse or rough object (and the colour cast of a fill) weigh more than the per-pixel term
    alone gives them."""
    sa = torch.from_numpy(np.ascontiguousarray(equirect.solid_angle_image(h, w), dtype=np.float32))
    sa = (sa / sa.mean())[None, None]                                    # [1, 1, H, W]
    scale = (target * sa).mean((1, 2, 3)) + 0.02                          # [B]
    loss = ((completed - target).abs() * sa).mean((1, 2, 3)) / scale
    for k in pools if lowfreq > 0 else ():
        if h % k or w % k:
            raise ValueError(f"completion_loss: pool {k} does not divide {h}x{w}")
        wsum = torch.nn.functional.avg_pool2d(sa, k)                      # [1, 1, H/k, W/k]
        a = torch.nn.functional.avg_pool2d(completed * sa, k) / wsum
        b = torch.nn.functional.avg_pool2d(target * sa, k) / wsum
        loss = loss + lowfreq * ((a - b).abs() * wsum).mean((1, 2, 3)) / scale
    return loss.mean()


def _lr(step: int, frac: float, cfg) -> float:
    """Linear warm-up over ``cfg.warmup`` steps, then cosine decay to 5 % over the fraction
    ``frac`` of the time budget that has passed (the run is bounded by time, so its step
    count is not known in advance)."""
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    x = min(1.0, max(0.0, frac))
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * x)))


def train(cfg: TrainCompletionConfig, progress: bool = True, command: str | None = None) -> dict:
    """Train and save the network; returns the log (also written beside the weights as JSON).

    Phases: the data (:func:`build_data`), the model and its optimiser, the samplers, a
    checkpoint to resume from (:func:`_resume`), the loop (:func:`_train_loop`), the weights
    and their card (:func:`_save`)."""
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    t_data = time.perf_counter()
    data = build_data(cfg, progress)
    t_data = time.perf_counter() - t_data
    model, opt = _model_and_optimiser(cfg)
    sampler = Sampler(data, cfg, cfg.seed + 7)
    val_batches = _validation_batches(data, cfg)
    run = _resume(cfg, model, opt, sampler)
    t0 = _train_loop(cfg, model, opt, sampler, val_batches, run, progress)
    return _save(cfg, model, data, run, t0, t_data, command)


@dataclass
class _Run:
    """Where a training run stands (fresh, or restored from its checkpoint)."""
    hist: list = field(default_factory=list)      # validation records, one per 100 steps
    step: int = 0
    step1_end: int | None = None                   # the first EV-conditioned step
    elapsed: float = 0.0                           # training seconds before this process


def _model_and_optimiser(cfg: TrainCompletionConfig):
    """(CompletionNet, AdamW): a new network, or ``cfg.init``'s weights."""
    net_cfg = C.CompletionConfig(base_channels=cfg.base_channels, prior=cfg.prior,
                                 train_resolution=(cfg.height, cfg.width), **cfg.net)
    model = C.CompletionNet(net_cfg)
    if cfg.init is not None:
        model.load_state_dict(C.load_weights(cfg.init, net_cfg).state_dict())
        log.info("initialised from %s", cfg.init)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, betas=(0.9, 0.999), weight_decay=0.01)
    return model, opt


def _validation_batches(data: dict, cfg: TrainCompletionConfig) -> list:
    """Two EV-0 and two EV-conditioned batches of a fixed sampler (seed 12345)."""
    val = Sampler(data, cfg, 12345)
    with torch.no_grad():
        return [val.batch(cfg.batch, "zero") for _ in range(2)] + \
               [val.batch(cfg.batch, "ev") for _ in range(2)]


def _resume(cfg: TrainCompletionConfig, model, opt, sampler: Sampler) -> _Run:
    """The run restored from ``cfg.checkpoint_path`` (model, optimiser, random streams),
    or a fresh one."""
    resumed = _load_checkpoint(cfg)
    if resumed is None:
        return _Run()
    model.load_state_dict(resumed["model"])
    opt.load_state_dict(resumed["opt"])
    sampler.rng.bit_generator.state = resumed["rng"]
    torch.set_rng_state(resumed["torch_rng"])
    run = _Run(resumed["hist"], resumed["step"], resumed["step1_end"], resumed["elapsed"])
    log.info("resumed %s at step %d (%.0f s)", cfg.checkpoint_path, run.step, run.elapsed)
    return run


def _train_loop(cfg: TrainCompletionConfig, model, opt, sampler: Sampler, val_batches: list,
                run: _Run, progress: bool) -> float:
    """Train until the time budget or the step limit; validate every 100 steps (to ``run.hist``
    and the metrics log), checkpoint on the clock, on SIGINT/SIGTERM and at the end.
    Returns the start time (``perf_counter``) the run's seconds count from."""
    budget = cfg.minutes * 60.0
    jsonl_name = f"{Path(cfg.out).stem}.{runlog.LOG_NAME}"     # (time, validation loss) records
    runlog.rewrite(Path(cfg.out).parent, [runlog.record("train-completion", **r) for r in run.hist],
                   name=jsonl_name)
    t0 = time.perf_counter() - run.elapsed
    clock = CheckpointClock(cfg.checkpoint_every, cfg.checkpoint_every_s)
    bar = tqdm(total=int(budget), desc="train-completion", unit="s", disable=not progress)
    with stop_signals() as guard:
        while run.step < cfg.max_steps:
            el = time.perf_counter() - t0
            if el >= budget:
                break
            frac = max(el / budget, run.step / cfg.max_steps)
            mode = "zero" if frac < cfg.step1_frac else "ev"
            if mode == "ev" and run.step1_end is None:
                run.step1_end = run.step
            loss = _train_step(cfg, model, opt, sampler, run.step, frac, mode)
            run.step += 1
            if run.step % 100 == 0 or run.step == 1:
                rec = _validation_record(cfg, model, val_batches, loss, run.step, t0, mode, opt)
                run.hist.append(rec)
                runlog.append(Path(cfg.out).parent, runlog.record("train-completion", **rec),
                              name=jsonl_name)
                bar.set_postfix(loss=rec["loss"], val0=rec["val_ev0"], valev=rec["val_ev"])
            if guard.signum is not None or clock.due(run.step):
                _save_checkpoint(cfg, model, opt, sampler, run.step, time.perf_counter() - t0,
                                 run.hist, run.step1_end)
                clock.mark()
                guard.raise_if_stopped(run.step, cfg.checkpoint_path)
            bar.n = int(min(budget, time.perf_counter() - t0))
            bar.refresh()
        bar.close()
        _save_checkpoint(cfg, model, opt, sampler, run.step, time.perf_counter() - t0, run.hist,
                         run.step1_end)
    return t0


def _train_step(cfg: TrainCompletionConfig, model, opt, sampler: Sampler, step: int,
                frac: float, mode: str) -> torch.Tensor:
    """One optimiser step on a batch of ``mode`` ("zero": EV 0, "ev": EV-conditioned), its
    gradient clipped at 1; a non-finite loss or gradient skips the update. Returns the loss."""
    for g in opt.param_groups:
        g["lr"] = _lr(step, frac, cfg)
    rgb, nor, msk, tgt, evs, lab = sampler.batch(cfg.batch, mode)
    out = model(rgb, nor, msk, evs, lab)
    loss = completion_loss(out.completed, tgt, cfg.height, cfg.width, cfg.lowfreq)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    gn = float(torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0))
    if math.isfinite(loss.item()) and math.isfinite(gn):
        opt.step()
    return loss


def _validation_record(cfg: TrainCompletionConfig, model, val_batches: list, loss, step: int,
                       t0: float, mode: str, opt) -> dict:
    """The history record of ``step``: the training loss and the per-pixel validation L1 of
    the EV-0 and the EV-conditioned batches."""
    with torch.no_grad():
        vl = [completion_loss(model(*b[:3], b[4], b[5]).completed, b[3], cfg.height,
                              cfg.width).item() for b in val_batches]        # per-pixel term
    return {"step": step, "time_s": round(time.perf_counter() - t0, 1), "mode": mode,
            "loss": round(loss.item(), 5), "val_ev0": round(float(np.mean(vl[:2])), 5),
            "val_ev": round(float(np.mean(vl[2:])), 5), "lr": opt.param_groups[0]["lr"]}


def _save(cfg: TrainCompletionConfig, model, data: dict, run: _Run, t0: float, t_data: float,
          command: str | None) -> dict:
    """Save the weights and their card (``<out stem>.json``); returns the card."""
    out_path = C.save_weights(model, cfg.out)
    info = {"command": command or " ".join(sys.argv), "steps": run.step,
            "step1_steps": run.step1_end,
            "train_seconds": round(time.perf_counter() - t0, 1), "data_seconds": round(t_data, 1),
            "parameters": C.count_parameters(model),
            "data": {"maps": int(len(data["maps"])), "masks": int(len(data["masks"])),
                     "poly_haven": sorted({str(n) for n, s in zip(data["names"], data["source"])
                                           if s == 0}), "held_out": list(cfg.held_out),
                     "init_maps": _init_maps(cfg.init)},
            "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
            "torch": torch.__version__, "history": run.hist}
    out_path.with_suffix(".json").write_text(json.dumps(runlog.json_safe(info), indent=1,
                                                        allow_nan=False))
    return info


def _init_maps(init) -> list | None:
    """The real maps the ``--init`` weights were fitted on (their model card,
    ``pano_data.trained_maps``), so the fine-tuned card names every map the weights saw;
    None without ``--init`` or when its card does not say."""
    maps = None if init is None else P.trained_maps(init)
    return None if maps is None else sorted(maps)


#: ``--out`` (``core.config.shared_options``) of ``comgs train-completion``.
OUT_OPTION = dict(type=Path, default=None, metavar="W.pt",
                  help=f"weights file (default {TrainCompletionConfig.out}; the shipped one, "
                       f"{DEFAULT_WEIGHTS}, is replaced only when named here)")


def add_arguments(ap) -> None:
    """The ``comgs train-completion`` flags (also ``python -m comgs_dr.stages.train_completion``):
    every scalar field of :class:`TrainCompletionConfig` as ``--field-name``
    (``core.config.add_config_arguments``), some also under the name users typed before
    (``--skies`` for ``n_sky``); ``--out`` and ``--quiet`` where ``ap`` lacks them (a parser
    not built on ``core.config.shared_options``)."""
    if not any(a.dest == "out" for a in ap._actions):
        ap.add_argument("--out", **OUT_OPTION)
        ap.add_argument("--quiet", action="store_true", help="no progress bars")
    # older spellings, paths, lists and choices (add_config_arguments makes plain typed flags)
    ap.add_argument("--res", "--height", dest="height", type=int, default=None,
                    help=f"panorama height, a multiple of 16 (width = 2x; default "
                         f"{TrainCompletionConfig.height})")
    ap.add_argument("--skies", "--n-sky", dest="n_sky", type=int, default=None)
    ap.add_argument("--rooms", "--n-rooms", dest="n_rooms", type=int, default=None)
    ap.add_argument("--masks", "--n-masks", dest="n_masks", type=int, default=None)
    ap.add_argument("--channels", "--base-channels", dest="base_channels", type=int, default=None)
    ap.add_argument("--prior", choices=("push_pull", "none"), default=None,
                    help="predict a residual on the push-pull fill, or the panorama directly "
                         "(none, default: the shipped weights)")
    ap.add_argument("--data-dir", type=Path, default=None, help="training-data cache folder")
    ap.add_argument("--maps", dest="maps_dir", type=Path, default=None,
                    help="folder of .hdr/.exr maps (default: shared/data/hdri)")
    ap.add_argument("--held-out", nargs="*", default=None, metavar="NAME",
                    help="map names (file stems) never trained on")
    ap.add_argument("--init", type=Path, default=None,
                    help="start from these weights (same architecture): fine-tuning")
    add_config_arguments(ap, TrainCompletionConfig, exclude=("width",))   # width = 2 × height


def config_from_args(args) -> TrainCompletionConfig:
    """The config of the flags ``args`` holds (what was not typed keeps its default)."""
    kw = config_overrides(args, TrainCompletionConfig)
    height = kw.get("height", TrainCompletionConfig.height)
    if height < 16 or height % 16:
        raise ValueError(f"--res must be a positive multiple of 16, got {height}")
    if "held_out" in kw:
        kw["held_out"] = tuple(kw["held_out"])
    return TrainCompletionConfig(**kw, width=2 * height)


def run_from_args(args) -> int:
    cfg = config_from_args(args)
    info = train(cfg, progress=not args.quiet, command=" ".join(sys.argv))
    last = info["history"][-1] if info["history"] else {}
    print(f"saved {cfg.out}: {info['steps']} steps in {info['train_seconds']} s "
          f"(+{info['data_seconds']} s data), {info['parameters']} parameters, "
          f"val L1 ev0={last.get('val_ev0')} ev={last.get('val_ev')}")
    return 0


if __name__ == "__main__":

    set_variant("llvm_ad_rgb")
    _ap = argparse.ArgumentParser(prog="comgs train-completion", description=__doc__,
                                  formatter_class=argparse.RawDescriptionHelpFormatter,
                                  parents=[shared_options(out=OUT_OPTION, mitsuba_variant=False)])
    add_arguments(_ap)
    sys.exit(run_from_args(_ap.parse_args()))
