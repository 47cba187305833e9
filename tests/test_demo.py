"""`comgs make-dataset scene` (the demo itself: tests/test_report.py)."""
import json
import math
import warnings

import numpy as np
import pytest

from comgs_dr import cli


def test_make_dataset_scene_cli(tmp_path):
    """`comgs make-dataset scene`: the scene preset's test case, with and without points."""
    from comgs_dr import cli
    from comgs_dr.data.load import load_dataset
    args = ["--views", "4", "--test-views", "2", "--res", "16", "--quiet"]
    assert cli.main(["make-dataset", "scene", "--out", str(tmp_path / "a"), "--points", "50", *args]) == 0
    d = load_dataset(tmp_path / "a")
    assert len(d.train) == 4 and len(d.test) == 2 and d.points.shape == (50, 3)
    assert np.abs(d.points).max() < 1.5                       # on the (normalised) scene
    assert cli.main(["make-dataset", "scene", "--out", str(tmp_path / "b"), "--points", "0", *args]) == 0
    assert load_dataset(tmp_path / "b").points is None
    # the scene preset starts from the points, else (with a warning) from the view frustum
    from comgs_dr.stages.reconstruct import RadianceConfig, initial_surfels
    cfg = RadianceConfig(preset="scene", init_points=300)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p, how = initial_surfels(d, cfg, np.random.default_rng(0))
    assert p.count == 50 and how.startswith("dataset points")
    with pytest.warns(UserWarning, match="without dataset points"):
        p, how = initial_surfels(load_dataset(tmp_path / "b"), cfg, np.random.default_rng(0))
    assert p.count == 300 and "frustum" in how


def test_demo_config_checks_the_object_light():
    """``object_light`` names how step 2 treats the object's capture light; anything else is
    refused before work, and the CLI offers the same two choices."""
    from comgs_dr.demo import PRESETS, DemoConfig
    assert PRESETS["default"].object_light == "learnt"
    assert DemoConfig(object_light="known").object_light == "known"
    with pytest.raises(ValueError, match="object_light"):
        DemoConfig(object_light="studio")
    assert cli.main(["demo", "--object-light", "studio"]) == 2
    assert cli.main(["demo", "--sky-views", "-1", "--out", "/nonexistent/demo"]) == 2
