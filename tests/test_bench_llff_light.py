"""benchmarks/llff_light_e2e.py at smoke-test size: a forward-facing capture of a real map,
step 1 with and without the far-field initialisation, the lighting scored at the placement."""
import numpy as np
import pytest

from bench_module import load_benchmark


def test_llff_light_e2e_smoke(tmp_path, capsys):
    from comgs_dr.data.synthetic import shared_data_dir
    maps = shared_data_dir() / "hdri"
    if not (maps / "kiara_1_dawn_1k.hdr").is_file():
        pytest.skip(f"shared maps not found at {maps}")
    mod = load_benchmark("llff_light_e2e")
    rows = mod.main(["--maps", "kiara_1_dawn_1k.hdr:162", "--rows", "1", "--cols", "3",
                     "--width", "48", "--height", "32", "--spp", "4", "--iterations", "10",
                     "--trace-res", "32", "--out", str(tmp_path)])
    assert [r["far_field"] for r in rows] == [True, False]
    for r in rows:
        assert np.isfinite(r["psnr_test"]) and r["power"] > 0 and 0.0 <= r["open_sky"] <= 1.0
    out = capsys.readouterr().out
    assert out.count("| kiara_1_dawn_1k:162 |") == 2
    with pytest.raises(FileNotFoundError, match="map not found"):
        mod.main(["--maps", "nothing.hdr", "--out", str(tmp_path)])
