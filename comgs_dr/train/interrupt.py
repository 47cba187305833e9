"""Faults a long run survives: SIGINT/SIGTERM write a checkpoint before exiting, and
checkpoints also go by wall time.

``stop_signals()`` is a context manager installing handlers for SIGINT and SIGTERM (main
thread only; elsewhere it does nothing) that only *record* the signal; the training loop
checks ``guard.signum`` after each step, writes its checkpoint and raises
:class:`TrainingInterrupted` (a ``KeyboardInterrupt``, so notebooks and scripts stop as they
would on Ctrl-C). A second signal while the checkpoint is written falls through to the
previous handler (Ctrl-C twice stops at once; the checkpoint write is atomic, so the last
complete checkpoint survives either way). ``CheckpointClock`` says when a checkpoint is due:
every ``every_iterations`` iterations or ``every_seconds`` of wall time, whichever comes
first. SIGKILL cannot be caught: what survives it is the atomic write
(``checkpoint.atomic_write_bytes``) and resuming from the last checkpoint.
"""
from __future__ import annotations

import signal
import threading
import time
from contextlib import contextmanager

NAMES = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}


class TrainingInterrupted(KeyboardInterrupt):
    """A run stopped by a signal after writing its checkpoint."""

    def __init__(self, signum: int, iteration: int, checkpoint):
        self.signum, self.iteration, self.checkpoint = signum, iteration, checkpoint
        super().__init__(f"{NAMES.get(signum, signum)} at iteration {iteration}: checkpoint "
                         f"written to {checkpoint}; run the same command again to resume")

    @property
    def exit_code(self) -> int:
        """The shell's convention, 128 + signal number (130 for SIGINT, 143 for SIGTERM)."""
        return 128 + int(self.signum)


class _Guard:
    def __init__(self):
        self.signum: int | None = None
        self._previous: dict = {}

    def _handle(self, signum, frame):
        if self.signum is not None:             # second signal: the previous behaviour
            prev = self._previous.get(signum, signal.SIG_DFL)
            signal.signal(signum, prev)
            if callable(prev):
                prev(signum, frame)
            else:
                signal.raise_signal(signum)
            return
        self.signum = signum

    def raise_if_stopped(self, iteration: int, checkpoint) -> None:
        if self.signum is not None:
            raise TrainingInterrupted(self.signum, iteration, checkpoint)


@contextmanager
def stop_signals():
    """Record SIGINT/SIGTERM instead of dying mid-step (see the module docstring)."""
    guard = _Guard()
    if threading.current_thread() is not threading.main_thread():
        yield guard
        return
    for s in NAMES:
        guard._previous[s] = signal.getsignal(s)
        signal.signal(s, guard._handle)
    try:
        yield guard
    finally:
        for s, prev in guard._previous.items():
            signal.signal(s, prev if prev is not None else signal.SIG_DFL)


class CheckpointClock:
    """Due every ``every_iterations`` iterations or ``every_seconds`` seconds of wall time
    since the last checkpoint (``None`` disables either)."""

    def __init__(self, every_iterations: int | None, every_seconds: float | None):
        self.every_iterations, self.every_seconds = every_iterations, every_seconds
        self.last = time.monotonic()

    def due(self, iteration: int) -> bool:
        by_count = bool(self.every_iterations) and iteration % self.every_iterations == 0
        by_time = (self.every_seconds is not None
                   and time.monotonic() - self.last >= self.every_seconds)
        return by_count or by_time

    def mark(self) -> None:
        self.last = time.monotonic()
