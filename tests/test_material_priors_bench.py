"""benchmarks/material_priors.py: its variant parser and a tiny end-to-end run."""
import numpy as np
import pytest
from bench_module import load_benchmark
from conftest import make_tiny_step1_run


def _bench():
    return load_benchmark("material_priors")


def test_variants_are_parsed_and_checked():
    from comgs_dr.stages.decompose import MaterialConfig
    pv = _bench().parse_variants
    v = pv("base:,sm:lambda_smooth=0.1,smooth_k=4,w:lambda_white=1,visibility=sops",
           MaterialConfig)
    assert v == {"base": {}, "sm": {"lambda_smooth": 0.1, "smooth_k": 4},
                 "w": {"lambda_white": 1, "visibility": "sops"}}
    for bad in ("", "x:no_such_field=1", "lambda_smooth=1", "a:,a:", ":lambda_smooth=1"):
        with pytest.raises(ValueError, match="--variants"):
            pv(bad, MaterialConfig)


def test_tiny_run_scores_every_variant(tmp_path, variant, capsys):
    (tmp_path / "t").mkdir()
    run, _ = make_tiny_step1_run(tmp_path / "t", n_surfels=1500)
    rows = _bench().main(["--runs", str(run), "--work", str(tmp_path / "w"),
                          "--variants", "base:,sm:lambda_smooth=1.0,rays=16,env_res=16,"
                          "probe_count=100,probe_res=8", "--iterations", "6", "--rays", "16"])
    assert set(rows) == {"run/base", "run/sm"}
    for r in rows.values():
        assert np.isfinite([r["psnr"], r["albedo_psnr"], r["metal"], r["nbr_diff"]]).all()
    assert "| run/sm |" in capsys.readouterr().out
    with pytest.raises(FileNotFoundError):
        _bench().main(["--runs", str(tmp_path / "nothing"), "--work", str(tmp_path / "w2")])
