"""The one training loop of step 1 and step 2: progress, evaluation schedule, the
(wall time, metric) log, checkpoints, time limit and resume.

A trainer is a :class:`TrainerBase` (the :class:`LoopTrainer` protocol plus the optional
hooks with their defaults). The loop calls ``step()`` until ``iteration`` reaches
``cfg.iterations``; every ``log_every`` iterations it appends a record
``{"iteration", "time_s", **log_fields(), **stats}`` to ``log``, and every ``eval_every``
(and at the last iteration) adds ``evaluate(eval_views)`` to it (evaluation time does not
count as training time). Given a
:class:`BestState`, every evaluation that returns ``psnr_select`` (a PSNR on *training* views,
so the test views never choose the state) and beats the best so far is ``snapshot()``-ed.
The config gives ``iterations``, ``log_every``, ``eval_every``, ``eval_views``,
``checkpoint_every``, ``checkpoint_every_s`` (wall time) and ``time_limit_s``. SIGINT/SIGTERM
during the loop write a checkpoint and raise ``interrupt.TrainingInterrupted``
(``train.interrupt``). With a ``jsonl_dir`` each record is also appended to ``metrics.jsonl``
as it is taken (``core.runlog``; rewritten from the restored log on resume and at the end),
so ``comgs report`` can plot a run that is still going.
"""
from __future__ import annotations

import abc
import json
import time
import warnings
from pathlib import Path
from typing import Protocol, runtime_checkable

import drjit as dr
from tqdm.auto import tqdm

from comgs_dr.core import runlog
from comgs_dr.train.checkpoint import atomic_write_text
from comgs_dr.train.interrupt import CheckpointClock, stop_signals

LOG_NAME = "train_log.json"


@runtime_checkable
class LoopTrainer(Protocol):
    """What :func:`run_loop` needs of a trainer."""

    iteration: int          # steps taken (restored on resume)
    elapsed: float          # training seconds so far (restored on resume)
    log: list               # the records so far

    def step(self) -> dict:
        """One optimisation step; the stats include ``loss`` and ``psnr_train``."""

    def evaluate(self, max_views: int | None = None) -> dict:
        """Scores on at most ``max_views`` views: ``psnr_test``, optionally ``psnr_select``."""

    def checkpoint(self) -> None:
        """Write the state to resume from."""


class TrainerBase(abc.ABC):
    """A :class:`LoopTrainer` with the loop's optional hooks and their defaults."""

    iteration: int
    elapsed: float
    log: list
    #: where :meth:`checkpoint` writes (named when a signal stops the run); None: unnamed
    checkpoint_path: Path | None = None

    @abc.abstractmethod
    def step(self) -> dict:
        """One optimisation step; the stats include ``loss`` and ``psnr_train``."""

    @abc.abstractmethod
    def evaluate(self, max_views: int | None = None) -> dict:
        """Scores on at most ``max_views`` views: ``psnr_test``, optionally ``psnr_select``."""

    @abc.abstractmethod
    def checkpoint(self) -> None:
        """Write the state to resume from."""

    def log_fields(self) -> dict:
        """Extra values of every record (e.g. the surfel count)."""
        return {}

    def bar_fields(self) -> dict:
        """The part of :meth:`log_fields` the progress bar shows."""
        return self.log_fields()

    def snapshot(self) -> dict:
        """A host copy of the state, for :class:`BestState`."""
        raise NotImplementedError(f"{type(self).__name__} keeps no best state")

    def restore(self, state: dict) -> None:
        """Install a :meth:`snapshot`."""
        raise NotImplementedError(f"{type(self).__name__} keeps no best state")


def zero_nonfinite_grads(opt, keys) -> int:
    """Replace non-finite gradient entries of ``opt[key]`` by 0 (so one bad ray cannot
    poison Adam); returns how many entries were replaced (arrays and tensors)."""
    bad = 0
    for key in keys:
        g = dr.grad(opt[key])
        flat = g.array if dr.is_tensor_v(g) else g
        ok = dr.isfinite(flat)
        nb = int(dr.count(~dr.all(ok) if dr.size_v(flat) > 1 else ~ok)[0])
        if nb:
            bad += nb
            fixed = dr.select(ok, flat, 0)
            dr.set_grad(opt[key], type(g)(fixed, g.shape) if dr.is_tensor_v(g) else fixed)
    return bad


def write_log(out_dir: Path, log: list, summary: dict | None = None, indent: int | None = 1) -> None:
    """``train_log.json``: {"summary": ..., "log": [records]} (atomic; a diverged loss's
    NaN is written as null, ``runlog.json_safe``: strict JSON parsers reject NaN)."""
    atomic_write_text(Path(out_dir) / LOG_NAME,
                      json.dumps(runlog.json_safe({"summary": summary, "log": log}),
                                 indent=indent, allow_nan=False))


class BestState:
    """The best evaluated state of a run (by ``psnr_select``) and the divergence check."""

    def __init__(self, tolerance_db: float = 0.5):
        self.psnr, self.iteration, self.state, self.tolerance_db = None, None, None, tolerance_db

    def offer(self, trainer, psnr: float, iteration: int) -> None:
        if psnr == psnr and (self.psnr is None or psnr > self.psnr):
            self.psnr, self.iteration, self.state = psnr, iteration, trainer.snapshot()

    def settle(self, trainer, final_psnr: float, iteration: int, desc: str,
               restore: bool = True) -> dict | None:
        """When the final state is more than ``tolerance_db`` worse than the best (or NaN),
        restore the best one (``restore``; else keep the final state) and return a record
        of the divergence (logged and warned, ``restored`` saying which state was kept);
        else None."""
        if self.state is None or (final_psnr == final_psnr
                                  and final_psnr >= self.psnr - self.tolerance_db):
            return None
        if restore:
            trainer.restore(self.state)
        note = {"best_psnr_select": round(self.psnr, 3), "best_iteration": self.iteration,
                "final_psnr_select": round(final_psnr, 3), "final_iteration": iteration,
                "restored": bool(restore)}
        kept = (f"the state of iteration {self.iteration} is kept" if restore
                else "the final state is kept (restore off)")
        warnings.warn(f"{desc}: training-view PSNR fell from {self.psnr:.2f} dB (iteration "
                      f"{self.iteration}) to {final_psnr:.2f} dB (iteration {iteration}); "
                      f"{kept}", stacklevel=2)
        return note

    def to_checkpoint(self) -> tuple[dict, dict | None]:
        """({``best_<name>``: array}, {psnr, iteration} or None): what a checkpoint keeps of
        the best state, so that a resumed run can still restore it."""
        if self.state is None:
            return {}, None
        return ({f"best_{k}": v for k, v in self.state.items()},
                {"psnr": self.psnr, "iteration": self.iteration})

    def from_checkpoint(self, arrays: dict, record: dict | None) -> None:
        """Take back what :meth:`to_checkpoint` wrote (nothing when ``record`` is None)."""
        if not record:
            return
        state = {k[5:]: v for k, v in arrays.items() if k.startswith("best_")}
        if state:
            self.psnr, self.iteration, self.state = (float(record["psnr"]),
                                                     int(record["iteration"]), state)


def run_loop(trainer: LoopTrainer, cfg, desc: str, progress: bool = True, log_dir: Path | None = None,
             best: BestState | None = None, jsonl_dir: Path | None = None,
             stage: str | None = None) -> bool:
    """Run ``trainer`` up to ``cfg.iterations`` (from wherever it resumed). With ``log_dir``
    the log is also written at every checkpoint; with ``jsonl_dir`` every record goes to its
    ``metrics.jsonl`` as stage ``stage`` (default ``desc``). Returns True if the time limit
    stopped it."""
    stage = stage or desc
    if jsonl_dir is not None:      # a resumed run drops the records after its checkpoint
        runlog.rewrite(jsonl_dir, runlog.from_train_log(stage, trainer.log))
    with stop_signals() as guard:
        return _loop(trainer, cfg, desc, progress, log_dir, best, jsonl_dir, stage, guard)


def _save(trainer, log_dir) -> None:
    trainer.checkpoint()
    if log_dir is not None:
        write_log(log_dir, trainer.log, indent=None)


def _loop(trainer, cfg, desc, progress, log_dir, best, jsonl_dir, stage, guard) -> bool:
    bar = tqdm(total=cfg.iterations, initial=trainer.iteration, desc=desc, unit="it",
               dynamic_ncols=True, disable=not progress)
    t0 = time.perf_counter() - trainer.elapsed
    stopped_early = False
    hooks = trainer if isinstance(trainer, TrainerBase) else None   # a bare LoopTrainer: none
    extra = hooks.log_fields if hooks else dict
    bar_extra = hooks.bar_fields if hooks else dict     # what the progress bar shows
    clock = CheckpointClock(cfg.checkpoint_every, getattr(cfg, "checkpoint_every_s", None))
    shown = {}                         # the bar names each PSNR and keeps the last test one
    while trainer.iteration < cfg.iterations:
        stats = trainer.step()
        trainer.elapsed = time.perf_counter() - t0
        it = trainer.iteration
        evaluate = it % cfg.eval_every == 0 or it == cfg.iterations
        if it % cfg.log_every == 0 or evaluate:
            rec = {"iteration": it, "time_s": round(trainer.elapsed, 3), **extra(), **stats}
            if evaluate:
                t_eval = time.perf_counter()
                rec.update(trainer.evaluate(cfg.eval_views))
                if best is not None and "psnr_select" in rec:
                    best.offer(trainer, rec["psnr_select"], it)
                t0 += time.perf_counter() - t_eval        # evaluation is not training time
            trainer.log.append(rec)
            if jsonl_dir is not None:
                runlog.append(jsonl_dir, runlog.from_train_log(stage, [rec])[0])
            shown["psnr_train"] = f"{stats['psnr_train']:.2f}"
            if "psnr_test" in rec:
                shown["psnr_test"] = f"{rec['psnr_test']:.2f}"
            bar.set_postfix(loss=f"{stats['loss']:.4f}", **shown, **bar_extra())
        bar.update(1)
        if guard.signum is not None:
            bar.close()
            _save(trainer, log_dir)
            guard.raise_if_stopped(it, hooks.checkpoint_path if hooks else None)
        if clock.due(it):
            _save(trainer, log_dir)
            clock.mark()
        if cfg.time_limit_s is not None and trainer.elapsed > cfg.time_limit_s:
            stopped_early = True
            break
    bar.close()
    trainer.checkpoint()
    return stopped_early


def plot_psnr(log: list, path: Path) -> None:
    """PNG of test (and train) PSNR against training wall-clock time."""
    import matplotlib  # heavy: loaded only when a plot is written
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ev = [r for r in log if "psnr_test" in r]
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    tr_ = [r for r in log if "psnr_train" in r]
    if tr_:
        ax.plot([r["time_s"] for r in tr_], [r["psnr_train"] for r in tr_], ".", ms=2, alpha=0.4,
                label="train view")
    if ev:
        ax.plot([r["time_s"] for r in ev], [r["psnr_test"] for r in ev], "o-", label="test views")
    ax.set_xlabel("training time [s]")
    ax.set_ylabel("PSNR [dB]")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def finish(trainer, out_dir: Path, summary: dict, stage: str | None = None) -> dict:
    """Write the final log with its summary, ``metrics.jsonl`` (as ``stage``, when given)
    and the PSNR-against-time plot."""
    write_log(out_dir, trainer.log, summary)
    if stage is not None:
        runlog.rewrite(out_dir, runlog.from_train_log(stage, trainer.log))
    plot_psnr(trainer.log, Path(out_dir) / "psnr_vs_time.png")
    return summary
