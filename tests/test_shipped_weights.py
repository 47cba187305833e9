"""The completion network weights shipped in the package: they load, give finite deterministic
brackets ordered by exposure, keep observed pixels, and complete unseen procedural panoramas
better than the mean fill."""
import json

import numpy as np
import pytest

from comgs_dr.data import pano_masks
from comgs_dr.lighting import backends
from comgs_dr.lighting import completion as C
from comgs_dr.lighting import pano_data as P
from comgs_dr.lighting.hdr import expose, fuse_brackets

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def backend():
    return backends.load_network_backend()


def test_shipped_weights_load_with_their_record(backend):
    assert backends.DEFAULT_WEIGHTS.is_file()
    assert backends.DEFAULT_WEIGHTS.stat().st_size < 16 * 2 ** 20
    cfg = backend.model.config
    assert cfg.version in C.SUPPORTED_VERSIONS and backend.resolution == cfg.train_resolution
    rec = json.loads(backends.DEFAULT_WEIGHTS.with_suffix(".json").read_text())
    assert "train_completion" in rec["command"] or "train-completion" in rec["command"]
    assert rec["steps"] > 100 and rec["config"].get("prior", "none") == cfg.prior
    assert not set(rec["data"]["held_out"]) & set(rec["data"]["poly_haven"])


@pytest.fixture(scope="module")
def samples():
    """Unseen procedural skies and rooms (seeds not used in training) with traced masks."""
    rng = np.random.default_rng(987654)
    maps = [P.sunsky_panorama(rng, 64, 128) for _ in range(3)] + \
           [P.room_panorama(rng, 64, 128, spp=16, seed=99) for _ in range(2)]
    masks = pano_masks.mask_bank(5, 64, 128, seed=4242, n_surfels=12000, points_per_scene=3)
    out = []
    for m, mk in zip(maps, masks):
        gt = m * P.auto_exposure(m)
        a = mk["alpha"]
        ldr = np.where(a[..., None] > 0, expose(gt, 0.0), 0.0).astype(np.float32)
        out.append((gt, ldr, mk["normal"], a))
    return out


def test_brackets_finite_ordered_deterministic_and_keep_observed(backend, samples):
    gt, ldr, nrm, a = samples[0]
    out = backend.complete(ldr, nrm, a, label=0)
    again = backend.complete(ldr, nrm, a, label=0)
    for ev in C.DEFAULT_EVS:
        assert np.isfinite(out[ev]).all() and out[ev].min() >= 0 and out[ev].max() <= 1
        np.testing.assert_array_equal(out[ev], again[ev])
    assert out[0.0].mean() > out[-2.5].mean() > out[-5.0].mean()
    full = a >= 1.0
    np.testing.assert_allclose(out[0.0][full], ldr[full], atol=1e-6)
    assert np.isfinite(fuse_brackets(out)).all()


def test_net_beats_mean_fill_on_unseen_panoramas(backend, samples):
    """Hole error of the EV-0 completion, averaged over 5 unseen panoramas."""
    fill = backends.FillBackend("mean")
    e_net, e_mean = [], []
    for gt, ldr, nrm, a in samples:
        hole = a < 0.05
        tgt = expose(gt, 0.0)
        e_net.append(np.abs(backend.complete(ldr, nrm, a, evs=(0.0,))[0.0] - tgt)[hole].mean())
        e_mean.append(np.abs(fill.complete(ldr, nrm, a, evs=(0.0,))[0.0] - tgt)[hole].mean())
    assert np.mean(e_net) < 0.9 * np.mean(e_mean), (e_net, e_mean)


def test_the_package_ships_only_the_weights_it_loads_at_run_time():
    """comgs_dr/lighting/weights holds the completion net, the light head and the scene-label
    model with their cards; the light head's cross-validation folds, which only benchmarks
    read, live in benchmarks/data/light_head_cv."""
    from pathlib import Path

    weights = Path(C.__file__).parent / "weights"
    assert sorted(p.name for p in weights.iterdir() if not p.name.startswith(".")) == [
        "completion.json", "completion.pt", "light_head.json", "light_head.pt",
        "scene_label.json"]
