"""benchmarks/light_head_in_scene.py: true gains of clipped regions, and a smoke run."""
import numpy as np
import pytest

from bench_module import load_benchmark

from comgs_dr.core.equirect import equirect_directions
from comgs_dr.lighting import envmap as em


def _sun_map(h=64, sun=500.0):
    d = equirect_directions(h, 2 * h)
    m = np.full((h, 2 * h, 3), 0.4)
    m[d @ np.array([0.6, 0.0, 0.8]) > np.cos(np.radians(6.0))] = sun
    return m


def test_true_gain_is_the_regions_power_over_its_clipped_pixels():
    b = load_benchmark("light_head_in_scene")
    from comgs_dr.lighting import lights as L
    rows = b.gains(_sun_map(), L.load_head(), 0, 3)
    assert len(rows) == 1                              # one clipped region: the sun
    sa, g, t = rows[0]
    assert t == pytest.approx(500.0, rel=1e-6)         # uniform 500 over white 1
    assert g >= 1.0 and sa > 0


def test_smoke_table(tmp_path, capsys):
    b = load_benchmark("light_head_in_scene")
    em.write_exr(tmp_path / "sunny.exr", _sun_map(128), "equirect")
    (tmp_path / "cache" / "sunny").mkdir(parents=True)
    np.save(tmp_path / "cache" / "sunny" / "probe_256.npy",
            np.repeat(np.repeat(_sun_map(128), 2, 0), 2, 1).astype(np.float32))
    assert b.main(["--cache", str(tmp_path / "cache"), "--maps", str(tmp_path / "sunny.exr")]) == 0
    out = capsys.readouterr().out
    row = [ln for ln in out.splitlines() if ln.startswith("| sunny (outdoor)")]
    assert len(row) == 1 and row[0].count("(") >= 4
