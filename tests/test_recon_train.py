"""Reconstruction step 1 end to end on a tiny synthetic object: improvement, resume, stability."""
import json

import mitsuba as mi
import numpy as np
import pytest

from conftest import make_tiny_object_dataset

from comgs_dr import cli
from comgs_dr.data.load import load_dataset
from comgs_dr.stages.reconstruct import CKPT_FORMAT, RadianceConfig, Trainer, train_radiance
from comgs_dr.train import checkpoint as ck
from comgs_dr.train.loop import LoopTrainer

trimesh = pytest.importorskip("trimesh")


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return make_tiny_object_dataset(tmp_path_factory.mktemp("tiny"))


def _cfg(**kw):
    base = dict(iterations=150, init_points=3000, eval_every=50, eval_views=4, log_every=10,
                checkpoint_every=50, max_hits=16, sh_degree=1, sh_increase_every=100, d2n_from=60,
                densify=dict(start=40, stop=120, interval=20, opacity_reset_interval=10 ** 6))
# (an opacity reset needs hundreds of iterations to recover: unit-tested in test_density)
    base.update(kw)
    return RadianceConfig(**base)


def test_training_improves_psnr(tiny_dataset, tmp_path):
    data = load_dataset(tiny_dataset)
    tr = Trainer(data, tmp_path / "probe", _cfg(), progress=False)
    assert isinstance(tr, LoopTrainer)            # what run_loop needs, on a real instance
    psnr0 = tr.evaluate()["psnr_test"]
    s = train_radiance(data, tmp_path / "run", _cfg(), progress=False)
    assert s["iterations"] == 150 and np.isfinite(s["psnr_test"])
    # a fitted radiance field must clearly beat its initialisation on held-out views
    # (measured on this set-up: 18.1 dB at init -> 20.5 dB in this test and 26-27 dB in a
    # script with max_hits 24; run-to-run spread is several dB at 150 iterations)
    assert s["psnr_test"] > psnr0 + 1.5, (psnr0, s["psnr_test"])
    log = json.loads((tmp_path / "run" / "train_log.json").read_text())
    assert [r["iteration"] for r in log["log"]][:3] == [10, 20, 30]
    assert all(np.isfinite(r["loss"]) for r in log["log"])
    assert any("densify_total" in r for r in log["log"])
    assert (tmp_path / "run" / "point_cloud.ply").exists() and (tmp_path / "run" / "psnr_vs_time.png").exists()
    p = tr.params().to_numpy()
    assert all(np.all(np.isfinite(v)) for v in p.values())


def test_kill_and_resume(tiny_dataset, tmp_path):
    data = load_dataset(tiny_dataset)
    run = tmp_path / "run"
    # "killed" after 40 iterations: a time limit of 0 s stops right after the first step,
    # so use a short run and then continue it to 60.
    s1 = train_radiance(data, run, _cfg(iterations=40, checkpoint_every=20), progress=False)
    assert s1["iterations"] == 40
    state = ck.load_checkpoint(run / ck.CKPT_NAME, CKPT_FORMAT)[2]
    assert state["iteration"] == 40
    (run / (ck.CKPT_NAME + ".abc.tmp")).write_bytes(b"half-written")   # a torn temp file is ignored
    s2 = train_radiance(data, run, _cfg(iterations=60, checkpoint_every=20), progress=False)
    assert s2["iterations"] == 60
    log = json.loads((run / "train_log.json").read_text())["log"]
    its = [r["iteration"] for r in log]
    assert its == sorted(its) and its[-1] == 60 and 40 in its and its.count(40) == 1
    # a corrupt checkpoint is a clear error, never silently restarted
    (run / ck.CKPT_NAME).write_bytes(b"garbage")
    with pytest.raises(ValueError, match="unreadable"):
        train_radiance(data, run, _cfg(iterations=80), progress=False)


def test_degenerate_surfels_are_repaired(tiny_dataset, tmp_path):
    data = load_dataset(tiny_dataset)
    tr = Trainer(data, tmp_path / "run", _cfg(iterations=30), progress=False)
    p = tr.params().to_numpy()
    p["log_scales"][:50] = 40.0          # huge
    p["log_scales"][50:100] = -40.0      # collapsed
    p["opacity_logit"][100:150] = 1e4    # saturated
    p["quats"][150:200] = 0.0            # zero rotation
    from comgs_dr.surfels import SurfelParams
    tr._resize(SurfelParams.from_numpy(**p), remap=None)
    for _ in range(30):
        st = tr.step()
        assert np.isfinite(st["loss"])
    q = tr.params().to_numpy()
    assert all(np.all(np.isfinite(v)) for v in q.values())
    assert q["log_scales"].max() <= np.log(tr.extent) + 1e-5
    assert np.abs(q["opacity_logit"]).max() <= 12.0 + 1e-5


def test_cli_reconstruct_and_render(tiny_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    rc = cli.main(["reconstruct", str(tiny_dataset), "--out", str(run), "--iterations", "30", "--quiet"])
    assert rc == 0
    rc = cli.main(["render", str(run), "--views", "test", "--quiet"])
    assert rc == 0
    m = json.loads((run / "metrics_test.json").read_text())
    assert m["views"] == 4 and np.isfinite(m["psnr"]) and 0 < m["ssim"] <= 1
    assert "normal_mae_deg" in m and np.isfinite(m["normal_mae_deg"])
    assert "depth_rel" in m
    assert (run / "render_test" / "000_color.png").exists()
    assert "PSNR" in capsys.readouterr().out


def test_cli_errors_name_the_path(tmp_path, capsys):
    assert cli.main(["reconstruct", str(tmp_path / "missing"), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert "missing" in capsys.readouterr().err
    assert cli.main(["render", str(tmp_path), "--quiet"]) == 2
    assert "run.json" in capsys.readouterr().err


def test_scaled_density_schedule_and_preset_defaults():
    from comgs_dr.stages.reconstruct import RadianceConfig, scaled_density_schedule
    assert scaled_density_schedule(1500) == {"stop": 750, "opacity_reset_interval": 375}
    assert scaled_density_schedule(1) == {"stop": 1, "opacity_reset_interval": 1}
    for preset, cap in (("object", 0.01), ("scene", 0.02)):
        c = RadianceConfig(preset=preset)
        assert c.densify["max_fraction"] == 0.0 and c.max_scale_frac == cap   # prune only
    assert RadianceConfig(preset="scene", densify={}).densify == {}          # explicit: as given


def test_trainer_snapshot_restore_round_trip(tiny_dataset, tmp_path):
    """Step 1's snapshot/restore gives back the same surfels and the same render."""
    cfg = _cfg(iterations=4, init_points=300, eval_views=1)
    tr = Trainer(load_dataset(tiny_dataset), tmp_path / "run", cfg, progress=False)
    for _ in range(2):
        tr.step()
    snap = tr.snapshot()
    before = np.array(mi.render(tr.scene, sensor=0))
    for _ in range(2):
        tr.step()
    assert not np.allclose(np.array(mi.render(tr.scene, sensor=0)), before)
    tr.restore(snap)
    after = tr.params().to_numpy()
    for k, v in snap.items():
        np.testing.assert_array_equal(after[k], v, err_msg=k)
    np.testing.assert_allclose(np.array(mi.render(tr.scene, sensor=0)), before, atol=1e-6)
    tr.step()                                              # the optimiser still works after it
    assert np.all(np.isfinite(tr.params().to_numpy()["means"]))


def _scaled(data, s: float):
    """The same capture with the world scaled by ``s`` (camera positions, points)."""
    import dataclasses

    from comgs_dr.data.types import SceneData

    def views(vs):
        out = []
        for v in vs:
            m = np.array(v.camera.to_world, np.float64)
            m[:3, 3] *= s
            out.append(dataclasses.replace(v, camera=dataclasses.replace(v.camera, to_world=m)))
        return out
    return SceneData(train=views(data.train), test=views(data.test),
                     points=None if data.points is None else data.points * s, colors=data.colors,
                     white_background=data.white_background)


def test_step1_is_scale_invariant(tiny_dataset, tmp_path):
    """The same object at 0.01, 1 and 100 scene units reconstructs to the same PSNR: learning
    rates, σ caps, clip planes, proxies and raster keys all scale with the scene."""
    data = load_dataset(tiny_dataset)
    got = {}
    for s in (0.01, 1.0, 100.0):
        summary = train_radiance(_scaled(data, s), tmp_path / f"s{s}", _cfg(iterations=40),
                                 progress=False)
        got[s] = summary["psnr_test"]
        assert summary["diverged"] is None
    # float rounding makes the three trajectories differ slightly (measured spread: see below)
    assert max(got.values()) - min(got.values()) < 0.3, got


def test_log_lerp_is_the_exponential_decay_bit_for_bit():
    """train.schedule.log_lerp gives exactly the values of the formula step 1 inlined
    before (positions' and the background's learning rates)."""
    import math

    from comgs_dr.train.schedule import log_lerp
    for start, end in ((1.6e-4, 1.6e-6), (0.01, 0.001), (5e-3, 5e-3), (2.0, 3.0)):
        for t in (0.0, 1e-7, 0.1, 1 / 3, 0.5, 0.999, 1.0):
            old = math.exp((1 - t) * math.log(start) + t * math.log(end))
            assert log_lerp(start, end, t) == old
