"""Faults survived: SIGINT/SIGTERM write a checkpoint, checkpoints also go by wall time,
SIGKILL at a random moment then resume ends like an uninterrupted run, a checkpoint is never
half-written, a failed write names the file and keeps the last checkpoint.

The SIGKILL tests run the real CLI in a subprocess (``python -m comgs_dr.cli``) on tiny inputs.
"""
import errno
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from conftest import make_tiny_object_dataset, make_tiny_step1_run

from comgs_dr.stages.decompose import CKPT_FORMAT as MAT_FORMAT
from comgs_dr.stages.reconstruct import CKPT_FORMAT as RECON_FORMAT
from comgs_dr.train import checkpoint as ck
from comgs_dr.train import interrupt
from comgs_dr.train.loop import TrainerBase, run_loop

# ----------------------------------------------------------------------------- in-process


class _Cfg:
    iterations, log_every, eval_every, eval_views = 50, 5, 1000, 1
    checkpoint_every, checkpoint_every_s, time_limit_s = 1000, None, None


class _Trainer(TrainerBase):
    """Counts; sends itself ``signum`` at iteration ``at``."""

    def __init__(self, signum=None, at=None):
        self.iteration, self.elapsed, self.log, self.saved = 0, 0.0, [], []
        self.signum, self.at, self.checkpoint_path = signum, at, "ckpt"

    def step(self):
        self.iteration += 1
        if self.iteration == self.at:
            os.kill(os.getpid(), self.signum)
        return {"loss": 1.0, "psnr_train": 1.0}

    def evaluate(self, n):
        return {}

    def checkpoint(self):
        self.saved.append(self.iteration)


@pytest.mark.parametrize("signum,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_checkpoints_then_stops(signum, code):
    before = signal.getsignal(signum)
    tr = _Trainer(signum, at=7)
    with pytest.raises(interrupt.TrainingInterrupted) as e:
        run_loop(tr, _Cfg(), "t", progress=False)
    assert tr.saved == [7] and e.value.iteration == 7 and e.value.exit_code == code
    assert e.value.checkpoint == "ckpt"                       # TrainerBase.checkpoint_path
    assert isinstance(e.value, KeyboardInterrupt) and "resume" in str(e.value)
    assert signal.getsignal(signum) is before                 # handler restored
    tr2 = _Trainer()
    assert run_loop(tr2, _Cfg(), "t", progress=False) is False and tr2.saved == [50]


def test_checkpoint_clock_by_count_and_wall_time(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(interrupt.time, "monotonic", lambda: now[0])
    c = interrupt.CheckpointClock(every_iterations=10, every_seconds=60.0)
    assert not c.due(3) and c.due(10)
    now[0] += 61.0
    assert c.due(11)                                           # by wall time
    c.mark()
    assert not c.due(12)
    assert not interrupt.CheckpointClock(None, None).due(10)


def test_failed_write_names_file_and_keeps_last_checkpoint(tmp_path, monkeypatch):
    p = tmp_path / ck.CKPT_NAME
    ck.atomic_write_bytes(p, b"first")

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(ck.os, "fsync", full)
    with pytest.raises(OSError) as e:
        ck.atomic_write_bytes(p, b"second")
    assert str(p) in str(e.value) and "previous version is kept" in str(e.value)
    assert e.value.errno == errno.ENOSPC
    assert p.read_bytes() == b"first" and list(tmp_path.iterdir()) == [p]   # no temp left


def test_stale_temporaries_are_removed_on_load(tmp_path):
    p = tmp_path / ck.CKPT_NAME
    (tmp_path / (ck.CKPT_NAME + ".abc123.tmp")).write_bytes(b"torn")
    assert ck.load_checkpoint(p, "x") is None
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- subprocesses


def _cmd(*args):
    return [sys.executable, "-m", "comgs_dr.cli", *map(str, args), "--quiet"]


def _env():
    return {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}


def _run(args, timeout=600):
    r = subprocess.run(_cmd(*args), capture_output=True, text=True, timeout=timeout, env=_env())
    assert r.returncode == 0, r.stderr[-2000:]
    return r


def _npz_state(path, fmt):
    """Read a checkpoint as a concurrent reader would (``np.load``; ``load_checkpoint`` also
    deletes the writer's temporary files, which only a resuming run may do)."""
    with np.load(path) as z:
        state = json.loads(bytes(z["state"]).decode())
        assert state["format"] == fmt and all(z[k].size >= 0 for k in z.files)
    return state


def _kill_at_random(args, watch, load, rng, timeout=300):
    """Start ``args``; once ``watch`` exists wait a random 0-0.5 s and SIGKILL it. While it
    runs, every checkpoint that exists must load (``load``): none is ever half-written."""
    p = subprocess.Popen(_cmd(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         env=_env())
    t_end, kill_at, loads = time.time() + timeout, None, 0
    while p.poll() is None and time.time() < t_end:
        if kill_at is None and watch.exists():
            kill_at = time.time() + rng.uniform(0.0, 0.5)
        if kill_at is not None and time.time() >= kill_at:
            p.send_signal(signal.SIGKILL)
            break
        if watch.exists():
            load()
            loads += 1
        time.sleep(0.05)
    err = p.communicate(timeout=60)[1].decode(errors="replace")
    assert loads >= 1
    assert p.returncode == -signal.SIGKILL, f"the run ended before the kill: {err[-2000:]}"
    return p.returncode


@pytest.fixture(scope="module")
def recon_data(tmp_path_factory):
    return make_tiny_object_dataset(tmp_path_factory.mktemp("faults_recon"))


def test_cli_unwritable_output_is_a_clear_error(recon_data, tmp_path, capsys):
    from comgs_dr import cli
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    rc = cli.main(["reconstruct", str(recon_data), "--out", str(blocker / "run"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 1 and str(blocker) in err and "Traceback" not in err, err


def _summary(run):
    return json.loads((run / "train_log.json").read_text())["summary"]


RECON = ("--iterations", 80, "--checkpoint-every", 10, "--eval-every", 40, "--eval-views", 4,
         "--log-every", 5, "--init-points", 2000, "--max-hits", 16, "--sh-degree", 1)


def test_reconstruct_sigkill_then_resume_matches_uninterrupted(recon_data, tmp_path):
    ref, run = tmp_path / "ref", tmp_path / "run"
    _run(["reconstruct", recon_data, "--out", ref, *RECON])
    _kill_at_random(["reconstruct", recon_data, "--out", run, *RECON],
                           run / ck.CKPT_NAME,
                           lambda: _npz_state(run / ck.CKPT_NAME, RECON_FORMAT),
                           np.random.default_rng())
    killed_at = ck.load_checkpoint(run / ck.CKPT_NAME, RECON_FORMAT)[2]["iteration"]
    assert 10 <= killed_at < 80
    _run(["reconstruct", recon_data, "--out", run, *RECON])
    assert not list(run.glob("*.tmp"))          # what the kill left was cleaned on resume
    a, b = _summary(ref), _summary(run)
    assert b["iterations"] == a["iterations"] == 80
    # measured: resumed vs uninterrupted differ by atomic-add rounding only (< 0.05 dB)
    print(f"reconstruct: killed after checkpoint {killed_at}; PSNR {a['psnr_test']:.4f} "
          f"uninterrupted, {b['psnr_test']:.4f} resumed")
    assert abs(a["psnr_test"] - b["psnr_test"]) < 0.3, (a["psnr_test"], b["psnr_test"])
    recs = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    its = [r["iteration"] for r in recs]
    assert its == sorted(set(its)) and its[-1] == 80          # no duplicated, stale records


def test_reconstruct_sigterm_checkpoints_and_resumes(recon_data, tmp_path):
    run = tmp_path / "run"
    base = ["reconstruct", recon_data, "--out", run, "--checkpoint-every", 100000,
            "--checkpoint-every-s", 1e6, "--log-every", 1, "--eval-views", 2,
            "--init-points", 2000, "--max-hits", 16]
    p = subprocess.Popen(_cmd(*base, "--iterations", 400, "--eval-every", 400), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         text=True, env=_env())
    jsonl = run / "metrics.jsonl"
    t_end = time.time() + 300
    while p.poll() is None and time.time() < t_end:
        if jsonl.exists() and jsonl.read_text().count("\n") >= 3:
            break
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM)
    err = p.communicate(timeout=120)[1]
    assert p.returncode == 143, err[-2000:]
    assert "SIGTERM" in err and "checkpoint written" in err and "Traceback" not in err
    it = ck.load_checkpoint(run / ck.CKPT_NAME, RECON_FORMAT)[2]["iteration"]
    assert 3 <= it < 400                 # only the signal wrote it (no periodic checkpoint due)
    _run([*base, "--iterations", it + 5, "--eval-every", it + 5])
    assert _summary(run)["iterations"] == it + 5


@pytest.fixture(scope="module")
def step1_run(tmp_path_factory):
    return make_tiny_step1_run(tmp_path_factory.mktemp("faults_mat"))[0]


DECOMP = ("--iterations", 60, "--rays", 16, "--env-res", 16, "--probes", 150,
          "--probe-res", 8, "--eval-every", 60, "--eval-views", 2, "--log-every", 5,
          "--checkpoint-every", 4)


def test_decompose_sigkill_then_resume_matches_uninterrupted(step1_run, tmp_path):
    ref, out = tmp_path / "ref", tmp_path / "mat"
    _run(["decompose", step1_run, "--out", ref, *DECOMP])
    _kill_at_random(["decompose", step1_run, "--out", out, *DECOMP], out / ck.CKPT_NAME,
                    lambda: _npz_state(out / ck.CKPT_NAME, MAT_FORMAT),
                    np.random.default_rng())
    _run(["decompose", step1_run, "--out", out, *DECOMP])
    a, b = _summary(ref), _summary(out)
    assert a["iterations"] == b["iterations"] == 60
    print(f"decompose: PSNR {a['psnr_test']:.4f} uninterrupted, {b['psnr_test']:.4f} resumed")
    assert abs(a["psnr_test"] - b["psnr_test"]) < 0.3, (a["psnr_test"], b["psnr_test"])


def test_train_completion_sigkill_then_resume_is_exact(tmp_path):
    from comgs_dr.lighting import completion as C
    from comgs_dr.stages.train_completion import TrainCompletionConfig
    maps = tmp_path / "maps"
    maps.mkdir()
    common = ["--data-dir", tmp_path / "data", "--maps", maps, "--minutes", 60,
              "--max-steps", 120, "--checkpoint-every", 5, "--skies", 2, "--rooms", 1,
              "--masks", 2, "--room-spp", 1, "--res", 16, "--channels", 8, "--batch", 2,
              "--threads", 1]
    ref, out = tmp_path / "ref.pt", tmp_path / "w.pt"
    _run(["train-completion", "--out", ref, *common])
    ckpt = TrainCompletionConfig(out=out).checkpoint_path
    _kill_at_random(["train-completion", "--out", out, *common], ckpt,
                    lambda: torch.load(ckpt, weights_only=True), np.random.default_rng())
    _run(["train-completion", "--out", out, *common])
    a, b = json.loads(ref.with_suffix(".json").read_text()), \
        json.loads(out.with_suffix(".json").read_text())
    assert a["steps"] == b["steps"] == 120
    assert [h["val_ev0"] for h in a["history"]] == [h["val_ev0"] for h in b["history"]]
    wa, wb = C.load_weights(ref).state_dict(), C.load_weights(out).state_dict()
    diff = max(float((wa[k] - wb[k]).abs().max()) for k in wa)
    print(f"train-completion: largest weight difference resumed vs uninterrupted {diff:.3g}")
    assert diff < 1e-5
