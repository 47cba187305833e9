"""Numeric flags of ``comgs`` (reconstruct, decompose, estimate-light, compose, render-comp,
demo, relight, export-mesh): ``-1``, ``0``, ``nan``, ``inf``, ``1e309`` and integers beyond 32 bits.

Contract: exit status 2 and a message naming the flag (or its config field), no
traceback, decided before any input is read (the inputs here do not exist, so a message
about them means the flag was not checked) and nothing written.
"""
import pytest
from hypothesis import given
from hypothesis import strategies as st
from robust_util import fuzz, slow

from comgs_dr import cli

HUGE = str(10 ** 30)


def _argv(tmp, command: str) -> list[str]:
    """A command line whose inputs do not exist (nothing heavy can start)."""
    return {
        "reconstruct": ["reconstruct", str(tmp / "no_data"), "--out", str(tmp / "out"),
                        "--quiet"],
        "decompose": ["decompose", str(tmp / "no_run"), "--out", str(tmp / "out"), "--quiet"],
        "estimate-light": ["estimate-light", str(tmp / "no.ply"), "--at", "0", "0", "0",
                           "--out", str(tmp / "out" / "env.exr")],
        "compose": ["compose", str(tmp / "no_run"), "--object", "a=" + str(tmp / "no_obj"),
                    "--placement", str(tmp / "no.json"), "--env", str(tmp / "no.exr"),
                    "--out", str(tmp / "out"), "--quiet"],
        "render-comp": ["render-comp", str(tmp / "no_comp"), "--cameras",
                        str(tmp / "no.json"), "--quiet"],
        "demo": ["demo", "--out", str(tmp / "out"), "--quiet"],
        "relight": ["relight", str(tmp / "no_run"), "--envmap", str(tmp / "no.exr"),
                    "--out", str(tmp / "out"), "--quiet"],
        "export-mesh": ["export-mesh", str(tmp / "no_run"), "--out", str(tmp / "out" / "m.ply"),
                        "--quiet"],
    }[command]


# (command, flag values, words of which one must be in the message)
CASES = [
    ("reconstruct", ["--iterations", "-1"], ["iterations"]),
    ("reconstruct", ["--iterations", "0"], ["iterations"]),
    ("reconstruct", ["--iterations", HUGE], ["--iterations"]),
    ("reconstruct", ["--lr-means", "nan"], ["--lr-means"]),
    ("reconstruct", ["--lr-means", "inf"], ["--lr-means"]),
    ("reconstruct", ["--lambda-d2n", "1e309"], ["--lambda-d2n"]),
    ("reconstruct", ["--time-limit", "nan"], ["--time-limit"]),
    ("reconstruct", ["--max-hits", HUGE], ["--max-hits"]),
    ("reconstruct", ["--sh-degree", "-1"], ["sh_degree"]),
    ("reconstruct", ["--resolution-scale", "-1"], ["--resolution-scale"]),
    ("reconstruct", ["--resolution-scale", "0"], ["--resolution-scale"]),
    ("decompose", ["--rays", "0"], ["rays"]),
    ("decompose", ["--rays", "-3"], ["rays"]),
    ("decompose", ["--rays", HUGE], ["--rays"]),
    ("decompose", ["--iterations", "-1"], ["iterations"]),
    ("decompose", ["--lr-env", "nan"], ["--lr-env"]),
    ("decompose", ["--time-limit", "inf"], ["--time-limit"]),
    ("decompose", ["--probes", HUGE], ["--probes"]),
    ("estimate-light", ["--at", "nan", "0", "0"], ["--at"]),
    ("estimate-light", ["--at", "0", "1e309", "0"], ["--at"]),
    ("estimate-light", ["--width", "-1"], ["width"]),
    ("estimate-light", ["--width", "0"], ["width"]),
    ("estimate-light", ["--height", HUGE], ["--height"]),
    ("estimate-light", ["--oct-res", "0"], ["oct_res"]),
    ("estimate-light", ["--max-hits", "-1"], ["max_hits"]),
    ("estimate-light", ["--supersample", "0"], ["supersample"]),
    ("estimate-light", ["--exclude-radius", "nan"], ["--exclude-radius"]),
    ("estimate-light", ["--exclude-radius", "-1"], ["exclude_radius"]),
    ("estimate-light", ["--net-resolution", "0", "64"], ["net_resolution"]),
    ("estimate-light", ["--n-lights", "-1"], ["n_lights"]),
    ("compose", ["--shadow-probes", "-1"], ["--shadow-probes"]),
    ("compose", ["--shadow-probes", "0"], ["--shadow-probes"]),
    ("compose", ["--shadow-probes", HUGE], ["--shadow-probes"]),
    ("render-comp", ["--res", "-1"], ["res"]),
    ("render-comp", ["--res", "0"], ["res"]),
    ("render-comp", ["--res", "16", HUGE], ["--res"]),
    ("render-comp", ["--rays", "0"], ["rays"]),
    ("render-comp", ["--rays", "-5"], ["rays"]),
    ("demo", ["--res", "-1"], ["resolution"]),
    ("demo", ["--res", "0"], ["resolution"]),
    ("demo", ["--res", HUGE], ["--res"]),
    ("relight", ["--scale", "nan"], ["--scale"]),
    ("relight", ["--rays", HUGE], ["--rays"]),
    ("export-mesh", ["--resolution", "-1"], ["resolution"]),
    ("export-mesh", ["--resolution", "0"], ["resolution"]),
    ("export-mesh", ["--resolution", HUGE], ["--resolution"]),
]


@pytest.mark.parametrize("command,flags,words", CASES,
                         ids=[f"{c}{''.join(f)}" for c, f, _ in CASES])
def test_bad_numeric_flag_is_exit_2(command, flags, words, tmp_path, capsys):
    code = cli.main(_argv(tmp_path, command) + flags)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and err.strip(), err
    assert any(w in err for w in words), f"the message does not name the flag: {err!r}"
    assert not (tmp_path / "out").exists(), "something was written before the flag was checked"


_FLOAT_FLAGS = [("reconstruct", "--lr-means"), ("reconstruct", "--time-limit"),
                ("decompose", "--lr-env"), ("estimate-light", "--exclude-radius"),
                ("relight", "--scale")]
_INT_FLAGS = [("reconstruct", "--iterations"), ("decompose", "--rays"),
              ("estimate-light", "--width"), ("compose", "--shadow-probes"),
              ("render-comp", "--rays"), ("demo", "--res")]


def _flag_value_test(n):
    bad_float = st.sampled_from(["nan", "-nan", "inf", "-inf", "1e309", "-1e400", "NaN",
                                 "Infinity"])
    huge_int = st.integers(2 ** 31, 10 ** 40).map(str) | st.integers(-(10 ** 40), -(2 ** 31)).map(str)

    @fuzz(n)
    @given(case=st.one_of(st.tuples(st.sampled_from(_FLOAT_FLAGS), bad_float),
                          st.tuples(st.sampled_from(_INT_FLAGS), huge_int)))
    def run(case):
        import contextlib
        import io
        import tempfile
        from pathlib import Path
        (command, flag), value = case
        err = io.StringIO()
        with tempfile.TemporaryDirectory() as d, contextlib.redirect_stderr(err):
            code = cli.main(_argv(Path(d), command) + [flag, value])
            written = (Path(d) / "out").exists()
        assert code == 2 and flag in err.getvalue() and not written, err.getvalue()
    return run


def test_non_finite_and_huge_values():
    """Any spelling of NaN/Inf/overflowing floats, any integer beyond 32 bits."""
    _flag_value_test(80)()


@slow
def test_non_finite_and_huge_values_many():
    _flag_value_test(400)()


def test_valid_values_still_reach_the_inputs(tmp_path, capsys):
    """Finite values pass the check: the error is then about the missing input."""
    code = cli.main(_argv(tmp_path, "estimate-light") + ["--width", "64", "--height", "32",
                                                          "--exclude-radius", "0.5"])
    assert code == 2 and "no.ply" in capsys.readouterr().err
    code = cli.main(_argv(tmp_path, "reconstruct") + ["--iterations", "5", "--lr-means", "1e-4"])
    assert code == 2 and "no_data" in capsys.readouterr().err
