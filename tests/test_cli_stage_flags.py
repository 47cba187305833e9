"""compose, render-comp, estimate-light and the train-* commands: every scalar field of
their configs is a flag that parses into the config, the spellings users typed before
still work, the Mitsuba variant's old names are aliases, and the stages' checks exit 2
naming the flag or the file."""
import argparse
import dataclasses
import typing

import pytest

from comgs_dr import cli
from comgs_dr.cli._flags import field_overrides
from comgs_dr.core.config import config_overrides
from comgs_dr.stages import train_completion, train_light_head, train_scene_label
from comgs_dr.stages.compose import ComposeConfig, compose_config, summary_text
from comgs_dr.stages.estimate_light import (
    BackendConfig,
    EstimateConfig,
    PlacementEstimateConfig,
    make_backend,
    placement_estimator,
    sky_warning,
)
from comgs_dr.stages.render_comp import RenderCompConfig, summary_line

#: (argv up to the flags, config, fields the command sets otherwise)
COMMANDS = [
    (["compose", "S", "--object", "a=O", "--placement", "p.json", "--out", "C"], ComposeConfig,
     set()),
    (["compose", "S", "--object", "a=O", "--placement", "p.json", "--out", "C"],
     PlacementEstimateConfig, set()),
    (["render-comp", "C", "--cameras", "t.json"], RenderCompConfig, {"materials"}),
    (["estimate-light", "s.ply", "--at", "0", "0", "0", "--out", "e.exr"], EstimateConfig,
     set()),
    (["estimate-light", "s.ply", "--at", "0", "0", "0", "--out", "e.exr"], BackendConfig,
     set()),
    (["train-completion"], train_completion.TrainCompletionConfig, {"width"}),
    (["train-light-head"], train_light_head.TrainLightHeadConfig, set()),
    (["train-scene-label"], train_scene_label.TrainSceneLabelConfig, set()),
]


def _scalar(hint):
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    tp = args[0] if len(args) == 1 else hint
    return tp if tp in (int, float, str, bool) else None


def _sub(name: str) -> argparse.ArgumentParser:
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


@pytest.mark.parametrize("argv, cls, own", COMMANDS, ids=lambda x: getattr(x, "__name__", None))
def test_every_scalar_field_is_a_flag_that_parses_into_the_config(argv, cls, own):
    parser = cli.build_parser()
    by_dest = {}
    for a in _sub(argv[0])._actions:
        by_dest.setdefault(a.dest, []).append(a)
    assert field_overrides(parser.parse_args(argv), cls) == {}          # nothing typed
    for name, hint in typing.get_type_hints(cls).items():
        tp = _scalar(hint)
        if tp is None or name in own:
            continue
        assert name in by_dest, (cls.__name__, name)
        action = next((a for a in by_dest[name] if "--" + name.replace("_", "-")
                       in a.option_strings), by_dest[name][0])
        value, expect = {int: ("3", 3), float: ("0.25", 0.25), bool: ("false", False),
                         str: ("x", "x")}[tp]
        if action.choices:
            value = expect = list(action.choices)[-1]
        typed = [action.option_strings[0], value]
        if isinstance(action, argparse._StoreConstAction):         # a switch (--no-cv)
            typed, expect = [action.option_strings[0]], action.const
        got = field_overrides(parser.parse_args(argv + typed), cls)
        assert got == {name: expect} and type(got[name]) is type(expect), (typed, got)


def test_older_spellings_parse_to_the_same_config():
    p = cli.build_parser()
    tc = train_completion.config_from_args(p.parse_args(
        ["train-completion", "--res", "32", "--skies", "3", "--channels", "8", "--held-out"]))
    assert (tc.height, tc.width, tc.n_sky, tc.base_channels, tc.held_out) == (32, 64, 3, 8, ())
    assert train_completion.config_from_args(p.parse_args(
        ["train-completion", "--height", "32", "--n-sky", "3", "--base-channels", "8",
         "--held-out"])) == tc
    tl = train_light_head.config_from_args(p.parse_args(
        ["train-light-head", "--bulbs", "--no-cv", "--white-core", "--draws", "5",
         "--heights", "64", "128", "--masks", "7"]))
    assert (tl.room_bulbs, tl.cv, tl.white_core, tl.draws_real, tl.heights, tl.n_masks) == \
        (True, False, True, 5, (64, 128), 7)
    assert train_light_head.config_from_args(p.parse_args(["train-light-head"])) == \
        train_light_head.TrainLightHeadConfig()
    ts = train_scene_label.config_from_args(p.parse_args(
        ["train-scene-label", "--draws", "3", "--rooms", "0", "--maps", "M"]))
    assert (ts.draws_real, ts.n_rooms, str(ts.maps_dir)) == (3, 0, "M")
    args = p.parse_args(["render-comp", "C", "--cameras", "t.json", "--res", "16", "8",
                         "--rays", "4", "--variant", "trace"])
    assert field_overrides(args, RenderCompConfig) == {"res": (16, 8), "rays": 4,
                                                        "variant": "trace"}
    args = p.parse_args(["estimate-light", "s.ply", "--at", "1", "2", "3", "--out", "e.exr",
                         "--net-resolution", "32", "64", "--backend", "sh", "--steps", "9"])
    assert EstimateConfig(**field_overrides(args, EstimateConfig)).net_resolution == (32, 64)
    assert BackendConfig(**field_overrides(args, BackendConfig)) == BackendConfig("sh", steps=9)


def test_trainer_flags_on_a_bare_parser():
    """``python -m comgs_dr.stages.train_*``: add_arguments brings --out and --quiet itself."""
    for module in (train_completion, train_light_head, train_scene_label):
        ap = argparse.ArgumentParser()
        module.add_arguments(ap)
        args = ap.parse_args(["--out", "x.pt", "--quiet", "--seed", "4"])
        assert args.quiet and config_overrides(args, type(module.config_from_args(args))) \
            == {"out": __import__("pathlib").Path("x.pt"), "seed": 4}


@pytest.mark.parametrize("argv", [["compose", "S", "--object", "a=O", "--placement", "p.json",
                                   "--out", "C"],
                                  ["estimate-light", "s.ply", "--at", "0", "0", "0", "--out",
                                   "e.exr"]])
def test_variant_is_a_hidden_alias_of_mitsuba_variant(argv, capsys):
    p = cli.build_parser()
    assert p.parse_args(argv).mitsuba_variant == "auto"
    assert p.parse_args(argv + ["--mitsuba-variant", "llvm_ad_rgb"]).mitsuba_variant == \
        "llvm_ad_rgb"
    assert p.parse_args(argv + ["--variant", "llvm_ad_rgb"]).mitsuba_variant == "llvm_ad_rgb"
    assert "--variant is now --mitsuba-variant" in capsys.readouterr().err
    assert "--variant " not in _sub(argv[0]).format_help()


def test_render_comp_variant_is_the_composite_variant():
    p = cli.build_parser()
    base = ["render-comp", "C", "--cameras", "t.json"]
    args = p.parse_args(base + ["--variant", "paste", "--variant-mitsuba", "llvm_ad_rgb"])
    assert args.variant == "paste" and args.mitsuba_variant == "llvm_ad_rgb"
    args = p.parse_args(base + ["--mitsuba-variant", "cuda_ad_rgb"])
    assert args.mitsuba_variant == "cuda_ad_rgb" and args.variant is None
    assert "--variant-mitsuba" not in _sub("render-comp").format_help()
    with pytest.raises(SystemExit):
        p.parse_args(base + ["--variant", "llvm_ad_rgb"])


@pytest.mark.parametrize("argv, words", [
    (["render-comp", "{t}/none", "--cameras", "t.json"], ["{t}/none/composition.json"]),
    (["render-comp", "{t}/none", "--cameras", "t.json", "--res", "1", "2", "3"], ["res"]),
    (["render-comp", "{t}/none", "--cameras", "t.json", "--variant", "paste", "--material",
      "a:albedo=1,0,0"], ["do not apply to variant 'paste'"]),
    (["render-comp", "{t}/none", "--cameras", "t.json", "--material", "a:gloss=1"],
     ["--material 'gloss=1'"]),
    (["compose", "{t}/run", "--object", "a={t}/obj", "--placement", "{t}/p.json", "--out",
      "{t}/out", "--light-head", "{t}/head.pt"], ["light head not found: {t}/head.pt"]),
    (["compose", "{t}/run", "--object", "a={t}/obj", "--placement", "{t}/p.json", "--out",
      "{t}/out", "--weights", "{t}/w.pt"], ["completion weights not found: {t}/w.pt"]),
    (["compose", "{t}/run", "--object", "a={t}/obj", "--placement", "{t}/p.json", "--out",
      "{t}/out", "--env", "{t}/e.exr", "--label", "auto"], ["--label", "with --env"]),
    (["compose", "{t}/run", "--object", "a={t}/obj", "--placement", "{t}/p.json", "--out",
      "{t}/out", "--env", "{t}/e.exr"], ["{t}/run"]),
    (["estimate-light", "{t}/s.ply", "--at", "0", "0", "0", "--out", "{t}/e.exr",
      "--backend", "sh"], ["scene file not found: {t}/s.ply"]),
    (["estimate-light", "{t}/s.ply", "--at", "0", "0", "0", "--out", "{t}/e.exr",
      "--backend", "sh", "--weights", "{t}/w.pt"], ["--weights does not apply"]),
    (["train-light-head", "--cv-out", "{t}/cv", "--no-cv"], ["--cv-out", "--no-cv"]),
    (["train-completion", "--res", "20"], ["--res", "multiple of 16"]),
])
def test_stage_checks_exit_2_naming_the_flag_or_file(argv, words, tmp_path, capsys):
    code = cli.main([a.format(t=tmp_path) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    assert all(w.format(t=tmp_path) in err for w in words), err
    assert not (tmp_path / "out").exists()


def test_compose_config_and_render_comp_config_checks():
    assert compose_config() is not compose_config("fast")
    cfg = compose_config("fast", 500, scene_views=3)
    assert (cfg.shadow.count, cfg.shadow.res, cfg.scene_views) == (500, 16, 3)
    with pytest.raises(ValueError, match="--shadow-probes must be ≥ 1"):
        compose_config(shadow_probes=0)
    with pytest.raises(ValueError, match="preset"):
        compose_config("slow")
    RenderCompConfig(res=(16, 8), rays=4, materials={"a": "scale=0.5"}).validate()
    for bad, what in ((dict(variant="x"), "variant"), (dict(res=(1, 2, 3)), "res"),
                      (dict(res=0), "res"), (dict(rays=0), "rays"),
                      (dict(materials={"a": "gloss=1"}), "--material"),
                      (dict(variant="paste", materials={"a": "scale=2"}), "'paste'")):
        with pytest.raises(ValueError, match=what):
            RenderCompConfig(**bad).validate()


def test_backend_and_placement_estimator_checks(tmp_path):
    for bc, res, what in ((BackendConfig("mean", weights="w.pt"), None, "--weights"),
                          (BackendConfig("sh"), (32, 64), "--net-resolution"),
                          (BackendConfig(diffusers_dir="d"), None, "--diffusers-dir"),
                          (BackendConfig("diffusers"), None, "needs --diffusers-dir")):
        with pytest.raises(ValueError, match=what):
            make_backend(bc, res)
    assert type(make_backend(BackendConfig("push_pull"))).__name__ == "FillBackend"
    assert placement_estimator("run", "out", env="e.exr") is None
    with pytest.raises(ValueError, match="--sun-from-shadows sets up the lighting estimation"):
        placement_estimator("run", "out", env="e.exr", sun_from_shadows="off")
    with pytest.raises(FileNotFoundError, match="scene-label model not found"):
        placement_estimator("run", "out", scene_label=str(tmp_path / "m.json"))


def test_sky_warning_and_printed_summaries():
    assert sky_warning(0.5, None, 0.0, "fix") is None
    assert sky_warning(0.01, None, 0.0, "do this").endswith("; do this")
    assert "open sky" in sky_warning(0.9, 0.01, 0.0, "")
    assert "clipped at EV 0" in sky_warning(0.9, None, 0.99, "")
    s = {"timings": dict.fromkeys(("lighting", "probe_placement", "occlusion_tracing",
                                   "total"), 1.0),
         "probes": {"shadow": 7, "shadow_per_object": {"a": 7}},
         "pairs": {"traced": ["x"], "reused": [], "culled": []}}
    text = summary_text(s, ComposeConfig(), "C")
    assert "shadow probes of 'a': 7 of the 10000 asked" in text
    assert text.endswith("7 shadow probes; occlusion pairs traced 1, reused 0, culled 0; wrote C")
    line = summary_line({"frames": 2, "variant": "sop", "first_frame_seconds": 1.0,
                         "frame_seconds": 0.5, "psnr": 30.0, "ssim": 0.9, "renders": "R"})
    assert line == ("2 frame(s) (sop), first 1.00 s (kernel compilation included), then "
                    "0.500 s/frame (median), PSNR 30.00 dB, SSIM 0.9000; renders in R")


def test_configs_document_every_field():
    """The config docstrings name each field (units and defaults live there)."""
    for cls in (ComposeConfig, RenderCompConfig, EstimateConfig, BackendConfig,
                PlacementEstimateConfig, train_completion.TrainCompletionConfig,
                train_light_head.TrainLightHeadConfig, train_scene_label.TrainSceneLabelConfig):
        missing = [f.name for f in dataclasses.fields(cls) if f.name not in cls.__doc__]
        assert not missing, (cls.__name__, missing)
