"""run.json: a run names its dataset and refuses one whose cameras changed after training."""
import json

import numpy as np
import pytest


def test_a_run_refuses_a_dataset_whose_cameras_changed_after_training(tmp_path):
    """run.json records the dataset's camera files' SHA-256: a later `comgs sfm` into the
    same folder (new cameras, a new frame) is refused by name, not rendered misplaced."""
    from comgs_dr.data.types import DatasetError
    from comgs_dr.train.run import load_run_dataset, read_run_info, write_run_info
    ds = tmp_path / "ds"
    ds.mkdir()
    frame = {"file_path": "./train/a", "transform_matrix": np.eye(4).tolist()}
    for split in ("train", "test"):
        (ds / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": 0.7, "frames": [frame]}))
    run = tmp_path / "run"
    write_run_info(run, ds, "scene", 1, False)
    info = read_run_info(run)
    assert len(info["cameras_sha256"]) == 64
    from comgs_dr.train.run import check_run_cameras
    check_run_cameras(run, info)                                   # unchanged: passes
    (ds / "transforms_test.json").write_text(json.dumps(
        {"camera_angle_x": 0.9, "frames": [frame]}))
    with pytest.raises(DatasetError, match="changed since this run was trained"):
        load_run_dataset(run, info, pixels=False)
    del info["cameras_sha256"]                                     # a run from before: passes
    check_run_cameras(run, info)
