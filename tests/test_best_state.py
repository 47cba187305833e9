"""The training loop keeps the best state (chosen on training views) and reports divergence."""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from comgs_dr.train.loop import BestState, LoopTrainer, TrainerBase, run_loop


@dataclasses.dataclass
class _Cfg:
    iterations: int = 12
    log_every: int = 1
    eval_every: int = 3
    eval_views: int = 1
    checkpoint_every: int = 10 ** 9
    time_limit_s: float | None = None


class _FakeTrainer:
    """A 'model' that is one number; its selection PSNR follows a given curve."""

    def __init__(self, curve):
        self.curve, self.iteration, self.elapsed, self.log = curve, 0, 0.0, []
        self.value = 0.0
        self.restored = None

    def step(self):
        self.iteration += 1
        self.value = float(self.iteration)
        return {"loss": 1.0, "psnr_train": 20.0}

    def evaluate(self, max_views=None):
        return {"psnr_test": 0.0, "psnr_select": self.curve[self.iteration]}

    def checkpoint(self):
        pass

    def snapshot(self):
        return {"value": self.value}

    def restore(self, state):
        self.value = state["value"]
        self.restored = state


def test_diverging_run_restores_its_best_state():
    curve = {3: 25.0, 6: 28.0, 9: 26.0, 12: 22.0}           # peaks at iteration 6, then falls
    tr, best = _FakeTrainer(curve), BestState(tolerance_db=0.5)
    run_loop(tr, _Cfg(), "test", progress=False, best=best)
    assert best.iteration == 6 and best.psnr == 28.0
    with pytest.warns(UserWarning, match="fell from 28.00 dB"):
        note = best.settle(tr, curve[12], tr.iteration, "test")
    assert tr.value == 6.0 and note["best_iteration"] == 6 and note["final_psnr_select"] == 22.0


def test_converging_run_keeps_its_final_state():
    curve = {3: 25.0, 6: 27.0, 9: 28.0, 12: 27.8}           # within 0.5 dB of the best
    tr, best = _FakeTrainer(curve), BestState(tolerance_db=0.5)
    run_loop(tr, _Cfg(), "test", progress=False, best=best)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert best.settle(tr, curve[12], tr.iteration, "test") is None
    assert tr.restored is None and tr.value == 12.0


def test_nan_final_state_is_replaced():
    curve = {3: 25.0, 6: float("nan"), 9: float("nan"), 12: float("nan")}
    tr, best = _FakeTrainer(curve), BestState()
    run_loop(tr, _Cfg(), "test", progress=False, best=best)
    assert best.iteration == 3                             # NaN is never "best"
    with pytest.warns(UserWarning):
        assert best.settle(tr, float("nan"), tr.iteration, "test") is not None
    assert tr.value == 3.0


def test_write_log_is_strict_json_with_nan_as_null(tmp_path):
    """A diverged run's NaN loss goes into train_log.json as null (strict parsers reject
    NaN); finite values are kept."""
    import json

    from comgs_dr.train.loop import LOG_NAME, write_log
    write_log(tmp_path, [{"loss": float("nan"), "psnr": 20.5}], {"psnr_test": float("inf")})
    txt = (tmp_path / LOG_NAME).read_text()
    d = json.loads(txt, parse_constant=lambda c: pytest.fail(f"non-strict constant {c}"))
    assert d == {"summary": {"psnr_test": None}, "log": [{"loss": None, "psnr": 20.5}]}


def test_restore_off_keeps_the_final_state_and_reports_it():
    curve = {3: 25.0, 6: 28.0, 9: 26.0, 12: 22.0}
    tr, best = _FakeTrainer(curve), BestState(tolerance_db=0.5)
    run_loop(tr, _Cfg(), "test", progress=False, best=best)
    with pytest.warns(UserWarning, match="restore off"):
        note = best.settle(tr, curve[12], tr.iteration, "test", restore=False)
    assert tr.restored is None and tr.value == 12.0
    assert note["restored"] is False and note["best_iteration"] == 6


def test_best_state_survives_a_checkpoint(tmp_path):
    """What a checkpoint keeps of the best state restores it after a resume."""
    import numpy as np

    from comgs_dr.train import checkpoint as ck

    class _Opt:
        state = {}
    best = BestState()
    best.psnr, best.iteration, best.state = 28.5, 1500, {"means": np.arange(6.0).reshape(2, 3)}
    arrays, record = best.to_checkpoint()
    ck.save_checkpoint(tmp_path / "c.npz", "fmt/1", {"means": np.zeros((2, 3)), **arrays},
                       _Opt(), {}, {"best": record})
    loaded, _, state = ck.load_checkpoint(tmp_path / "c.npz", "fmt/1")
    again = BestState()
    again.from_checkpoint(loaded, state["best"])
    assert again.psnr == 28.5 and again.iteration == 1500
    np.testing.assert_array_equal(again.state["means"], best.state["means"])
    empty = BestState()
    empty.from_checkpoint(loaded, None)                   # a run that never evaluated
    assert empty.state is None


def test_both_trainers_implement_the_loop_interface():
    """Step 1's and step 2's trainers are concrete TrainerBase subclasses (so LoopTrainers);
    a bare LoopTrainer without the optional hooks runs too."""
    import inspect

    from comgs_dr.stages.decompose import MaterialTrainer
    from comgs_dr.stages.reconstruct import Trainer
    for cls in (Trainer, MaterialTrainer):
        assert issubclass(cls, TrainerBase) and not inspect.isabstract(cls), cls
        assert isinstance(cls.checkpoint_path, property)
    assert Trainer.snapshot is not TrainerBase.snapshot      # step 1 keeps its best state
    assert Trainer.log_fields is not TrainerBase.log_fields
    assert MaterialTrainer.log_fields is TrainerBase.log_fields

    class _Minimal:                                       # only the protocol's members
        def __init__(self):
            self.iteration, self.elapsed, self.log = 0, 0.0, []

        def step(self):
            self.iteration += 1
            return {"loss": 1.0, "psnr_train": 20.0}

        def evaluate(self, max_views=None):
            return {"psnr_test": 19.0}

        def checkpoint(self):
            pass

    tr = _Minimal()
    assert isinstance(tr, LoopTrainer) and not isinstance(tr, TrainerBase)
    assert isinstance(_FakeTrainer({}), LoopTrainer)
    assert run_loop(tr, _Cfg(), "test", progress=False) is False and tr.iteration == 12
    assert set(tr.log[0]) == {"iteration", "time_s", "loss", "psnr_train"}

    class _Hooked(_Minimal, TrainerBase):
        def log_fields(self):
            return {"surfels": 7}

    tr = _Hooked()
    assert tr.bar_fields() == {"surfels": 7} and tr.checkpoint_path is None
    run_loop(tr, _Cfg(), "test", progress=False)
    assert tr.log[0]["surfels"] == 7
    with pytest.raises(NotImplementedError):
        tr.snapshot()
