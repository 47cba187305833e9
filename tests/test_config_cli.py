"""Stage configs on the command line (comgs_dr.core.config) and the CLI flags built from them."""
import argparse
import dataclasses

import pytest

from comgs_dr import cli
from comgs_dr.core.config import add_config_arguments, config_overrides


@dataclasses.dataclass
class _Cfg:
    iterations: int = 10
    rate: float = 0.5
    name: str = "a"
    flag: bool = False
    limit: float | None = None
    table: dict | None = None          # not a scalar: no flag


def test_flags_from_fields_and_only_typed_overrides():
    p = argparse.ArgumentParser()
    p.add_argument("--iterations", type=int, dest="iterations", help="hand-written")
    add_config_arguments(p, _Cfg)
    flags = {a.dest for a in p._actions}
    assert {"iterations", "rate", "name", "flag", "limit"} <= flags and "table" not in flags
    assert config_overrides(p.parse_args([]), _Cfg) == {}
    got = config_overrides(p.parse_args(["--rate", "2", "--flag", "yes", "--limit", "3",
                                         "--iterations", "7"]), _Cfg)
    assert got == {"rate": 2.0, "flag": True, "limit": 3.0, "iterations": 7}
    with pytest.raises(SystemExit):
        p.parse_args(["--flag", "maybe"])


def test_reconstruct_and_decompose_flags_cover_their_configs():
    from comgs_dr.stages.decompose import MaterialConfig
    from comgs_dr.stages.reconstruct import RadianceConfig
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, cls, skip in (("reconstruct", RadianceConfig, {"preset", "densify"}),
                            ("decompose", MaterialConfig, set())):
        dests = {a.dest for a in sub.choices[name]._actions}
        scalar = {f.name for f in dataclasses.fields(cls)
                  if f.type.split(" |")[0] in ("int", "float", "str", "bool")}
        assert scalar - skip <= dests, (name, scalar - skip - dests)
    args = parser.parse_args(["decompose", "RUN", "--lr-env", "0.02", "--no-indirect"])
    cfg = MaterialConfig(**config_overrides(args, MaterialConfig))
    assert cfg.lr_env == 0.02 and cfg.indirect is False and cfg.rays == MaterialConfig.rays


def test_help_names_the_presets_own_defaults():
    """``--lr-scales`` is 5e-3 in the dataclass but 1e-3 in the object preset: --help says both."""
    p = argparse.ArgumentParser()
    add_config_arguments(p, _Cfg, presets={"fast": {"rate": 0.9}, "slow": {"iterations": 99}})
    helps = {a.dest: a.help for a in p._actions}
    assert helps["rate"] == "(default 0.5; fast preset 0.9)"
    assert helps["iterations"] == "(default 10; slow preset 99)" and helps["name"] == "(default 'a')"
    from comgs_dr.stages.reconstruct import PRESETS
    assert f"object preset {PRESETS['object']['lr_scales']!r}" in _subhelp("reconstruct")


def _subhelp(name: str) -> str:
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name].format_help()
