"""Every command's flags come from its config dataclass (cli._flags over core.config): each
scalar field is a ``--field-name`` flag that parses into the config, the spellings users
typed before still work, and bad values exit 2 naming the problem."""
import argparse
import dataclasses
import typing

import pytest

from comgs_dr import cli
from comgs_dr.cli._flags import field_overrides
from comgs_dr.data.composition_dataset import CompositionDatasetConfig
from comgs_dr.data.llff_synthetic import LLFFDatasetConfig
from comgs_dr.data.synthetic import ObjectDatasetConfig, SceneDatasetConfig
from comgs_dr.demo import DemoConfig
from comgs_dr.eval.report import ReportConfig
from comgs_dr.stages.decompose import MaterialConfig
from comgs_dr.stages.export_mesh import MeshConfig
from comgs_dr.stages.reconstruct import RadianceConfig
from comgs_dr.stages.relight import RelightConfig
from comgs_dr.stages.render_run import RenderConfig
from comgs_dr.stages.cut_object import CutConfig
from comgs_dr.stages.place import PlaceConfig
from comgs_dr.stages.sfm import SfmConfig

#: (argv up to the flags, config, fields the command sets itself)
COMMANDS = [
    (["sfm", "PHOTOS", "--out", "D"], SfmConfig, set()),
    (["make-dataset", "object", "--out", "D"], ObjectDatasetConfig, {"out_dir", "variant"}),
    (["make-dataset", "scene", "--out", "D"], SceneDatasetConfig, set()),
    (["make-dataset", "llff", "--out", "D"], LLFFDatasetConfig, {"out_dir", "variant"}),
    (["make-dataset", "composition", "--out", "D"], CompositionDatasetConfig,
     {"out_dir", "variant"}),
    (["demo"], DemoConfig, {"out_dir", "progress"}),
    (["report", "RUN"], ReportConfig, set()),
    (["reconstruct", "DATA", "--out", "RUN"], RadianceConfig, {"preset"}),
    (["render", "RUN"], RenderConfig, set()),
    (["export-mesh", "RUN", "--out", "m.ply"], MeshConfig, set()),
    (["cut", "RUN", "--out", "O"], CutConfig, set()),
    (["decompose", "RUN"], MaterialConfig, set()),
    (["relight", "RUN", "--envmap", "e.exr"], RelightConfig, set()),
    (["place", "S", "--object", "a=O", "--view", "0", "--pixel", "1", "2", "--out", "t.json"],
     PlaceConfig, set()),
]


def _scalar(hint):
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    tp = args[0] if len(args) == 1 else hint
    return tp if tp in (int, float, str, bool) else None


def _command_parser(parser, argv):
    """The (sub)parser that parses the flags after ``argv``'s command words."""
    for word in argv:
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)),
                   None)
        if sub is None or word not in sub.choices:
            break
        parser = sub.choices[word]
    return parser


@pytest.mark.parametrize("argv, cls, own", COMMANDS, ids=lambda x: getattr(x, "__name__", None))
def test_every_scalar_field_is_a_flag_that_parses_into_the_config(argv, cls, own):
    parser = cli.build_parser()
    sub = _command_parser(parser, argv)
    by_flag = {s: a for a in sub._actions for s in a.option_strings}
    untyped = field_overrides(parser.parse_args(argv), cls)
    assert set(untyped) <= own, untyped                              # nothing typed
    for name, hint in typing.get_type_hints(cls).items():
        tp = _scalar(hint)
        if tp is None or name in own:
            continue
        flag = "--" + name.replace("_", "-")
        assert flag in by_flag, (cls.__name__, flag)
        action = by_flag[flag]
        value, expect = {int: ("3", 3), float: ("0.25", 0.25), bool: ("false", False),
                         str: ("x", "x")}[tp]
        if action.choices:
            value = expect = list(action.choices)[-1]
        typed = [flag, value]
        if isinstance(action, argparse._StoreConstAction):         # a switch (--sun-view)
            typed, expect = [flag], action.const
        got = {k: v for k, v in field_overrides(parser.parse_args(argv + typed), cls).items()
               if k not in own}
        assert got == {name: expect} and type(got[name]) is type(expect), (flag, got)


def test_reconstruct_takes_every_sfm_flag():
    """``comgs reconstruct PHOTOS`` runs SfM first: every scalar SfmConfig field is a flag of
    it, spelled as ``comgs sfm`` spells it unless reconstruct has that flag (``--sfm-seed``),
    and parses into the SfmConfig (``cli.sfm.sfm_flags_config``); the preset is left to the
    input (object for a dataset, scene for photos)."""
    from comgs_dr.cli.sfm import sfm_flags_config
    parser = cli.build_parser()
    argv = ["reconstruct", "DATA", "--out", "RUN"]
    sub = _command_parser(parser, argv)
    by_flag = {s: a for a in sub._actions for s in a.option_strings}
    assert sfm_flags_config(parser.parse_args(argv)) == (SfmConfig(), [])
    assert parser.parse_args(argv).preset is None and parser.parse_args(argv).sfm_out is None
    for name, hint in typing.get_type_hints(SfmConfig).items():
        tp = _scalar(hint)
        flag = "--" + name.replace("_", "-")
        if flag in by_flag and by_flag[flag].dest != "sfm_" + name:
            flag = "--sfm-" + name.replace("_", "-")             # reconstruct's own --seed
        assert by_flag[flag].dest == "sfm_" + name, flag
        value, expect = {int: ("3", 3), float: ("0.25", 0.25), bool: ("false", False),
                         str: ("x", "x")}[tp]
        if by_flag[flag].choices:
            value = expect = list(by_flag[flag].choices)[-1]
        if name in ("max_size", "max_features"):                    # >= 64
            value, expect = "640", 640
        cfg, typed = sfm_flags_config(parser.parse_args(argv + [flag, value]))
        assert typed == [name] and getattr(cfg, name) == expect, flag
    args = parser.parse_args(argv + ["--seed", "4", "--sfm-seed", "5", "--max-size", "800",
                                     "--sfm-out", "S"])
    assert field_overrides(args, RadianceConfig) == {"seed": 4}
    assert sfm_flags_config(args)[0] == SfmConfig(seed=5, max_size=800) and args.sfm_out == "S"
    with pytest.raises(ValueError, match="max_size"):
        sfm_flags_config(parser.parse_args(argv + ["--max-size", "10"]))


def test_old_spellings_parse_into_the_same_fields():
    p = cli.build_parser()

    def fields(cls, *argv):
        return field_overrides(p.parse_args(list(argv)), cls)

    assert fields(ObjectDatasetConfig, "make-dataset", "object", "--out", "D", "--views", "3",
                  "--test-views", "4", "--res", "16", "--rings", "10", "20", "--base-color",
                  "0.1", "0.2", "0.3", "--up", "z", "--no-texture", "--relight", "--fov",
                  "45") == dict(n_train=3, n_test=4, resolution=16, train_rings_deg=(10.0, 20.0),
                                base_color=(0.1, 0.2, 0.3), up_axis="z", texture=None,
                                relight_envmaps=(), fov_deg=45.0)
    assert fields(SceneDatasetConfig, "make-dataset", "scene", "--out", "D", "--views", "5",
                  "--points", "0") == dict(n_train=5, points=0)
    assert fields(LLFFDatasetConfig, "make-dataset", "llff", "--out", "D", "--downscale", "2",
                  "4", "--no-backdrop", "--pitch", "5", "--envmap-rotate", "30") == dict(
        downscales=(2, 4), backdrop=False, pitch_deg=5.0, envmap_rotate_deg=30.0)
    assert fields(CompositionDatasetConfig, "make-dataset", "composition", "--out", "D",
                  "--points", "7", "--sun-view", "--comp-res", "24", "--objects",
                  "spot,teapot") == dict(sfm_points=7, sun_view=True, comp_resolution=24,
                                         objects="spot,teapot")
    assert fields(DemoConfig, "demo", "--res", "24", "--comp-res", "32", "--object-light",
                  "known") == dict(resolution=24, comp_resolution=32, object_light="known")
    assert fields(MaterialConfig, "decompose", "RUN", "--probes", "9", "--no-indirect",
                  "--time-limit", "5") == dict(probe_count=9, indirect=False, time_limit_s=5.0)
    assert fields(RadianceConfig, "reconstruct", "DATA", "--out", "R", "--no-restore",
                  "--time-limit", "2", "--iterations", "7", "--scene") == dict(
        preset="scene", restore_best=False, time_limit_s=2.0, iterations=7)
    args = p.parse_args(["reconstruct", "DATA", "--out", "R", "--densify"])
    assert args.densify_scaled and "densify" not in field_overrides(args, RadianceConfig)
    assert fields(RelightConfig, "relight", "RUN", "--envmap", "e.exr", "--scale", "2",
                  "--material", "roughness=0.2", "--material-mask", "box:0,0,0,1,1,1") == dict(
        envmap_scale=2.0, material="roughness=0.2", material_mask="box:0,0,0,1,1,1")
    # the presets still fill what is not typed
    args = p.parse_args(["demo", "--preset", "tiny", "--res", "16"])
    assert args.preset == "tiny" and field_overrides(args, DemoConfig) == {"resolution": 16}


def test_defaults_the_commands_had_are_the_configs():
    assert (LLFFDatasetConfig().rows, LLFFDatasetConfig().downscales) == (4, (8,))
    assert CompositionDatasetConfig().probe_height == 128
    assert (SceneDatasetConfig().n_train, SceneDatasetConfig().points) == (60, 20_000)
    assert (RelightConfig().rays, RelightConfig().sampling, RelightConfig().views) == \
        (256, "mis", "test")
    assert RenderConfig().views == "test"


def test_shared_options_and_the_old_variant_flag(capsys):
    p = cli.build_parser()
    for argv in (["render", "RUN"], ["make-dataset", "llff", "--out", "D"],
                 ["relight", "RUN", "--envmap", "e.exr"], ["export-mesh", "R", "--out", "m.ply"]):
        args = p.parse_args(argv + ["--quiet", "--mitsuba-variant", "llvm_ad_rgb"])
        assert args.mitsuba_variant == "llvm_ad_rgb" and args.quiet
        assert p.parse_args(argv + ["--variant", "cuda_ad_rgb"]).mitsuba_variant == "cuda_ad_rgb"
        assert "--variant is now --mitsuba-variant" in capsys.readouterr().err
    assert p.parse_args(["demo"]).out is None                       # DemoConfig's out_dir
    assert not hasattr(p.parse_args(["demo"]), "mitsuba_variant")   # the demo picks auto


@pytest.mark.parametrize("argv, message", [
    (["make-dataset", "scene", "--points", "-1"], "points must be >= 0"),
    (["make-dataset", "llff", "--rows", "0"], "--rows must be >= 1"),
    (["make-dataset", "llff", "--envmap-rotate", "30"], "--envmap-rotate needs --envmap"),
    (["make-dataset", "object", "--views", "0"], "n_train must be >= 1"),
    (["make-dataset", "composition", "--probe-height", "-1"], "probe_height must be in"),
    (["demo", "--res", "4"], "DemoConfig.resolution must be an integer >= 8"),
])
def test_bad_values_exit_2_before_writing(tmp_path, capsys, argv, message):
    out = tmp_path / "o"
    flag = ["--out", str(out)]
    assert cli.main(argv[:2] + flag + argv[2:] if argv[0] == "make-dataset"
                    else argv + flag) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_relight_checks_its_config(tmp_path, capsys):
    assert cli.main(["relight", str(tmp_path), "--envmap", "e.exr",
                     "--material-mask", "box:0,0,0,1,1,1"]) == 2
    assert "material_mask needs material" in capsys.readouterr().err
    assert cli.main(["relight", str(tmp_path), "--envmap", "e.exr", "--material", "rough=1"]) == 2
    assert cli.main(["relight", str(tmp_path), "--envmap", "e.exr", "--views", "all"]) == 2
    assert cli.main(["render", str(tmp_path), "--max-hits", "0"]) == 2
    assert "max_hits must be >= 1" in capsys.readouterr().err
    with pytest.raises(ValueError, match="sampling"):
        RelightConfig(sampling="best")
    with pytest.raises(ValueError, match="visibility"):
        RelightConfig(visibility="probes")
    from comgs_dr.stages.relight import relight_run
    with pytest.raises(TypeError):
        relight_run(tmp_path, "e.exr", ray=4)                # not a RelightConfig field
    assert dataclasses.replace(RelightConfig(), rays=4).edit() is None


def test_the_module_docstring_lists_every_command_in_order():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    listed = [line.split()[0] for line in cli.__doc__.split("Commands")[1].split("\n\n")[1]
              .splitlines()]
    assert listed == list(sub.choices)


def test_probe_limit_agrees_with_the_renderer():
    from comgs_dr.data import composition_dataset, placement_probe
    assert composition_dataset.PROBE_MAX_HEIGHT == placement_probe.MAX_HEIGHT
