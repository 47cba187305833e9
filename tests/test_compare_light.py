"""`comgs compare-light EST TRUE`: the lighting scores of an estimate against the true light."""
import json

import numpy as np

from comgs_dr import cli
from comgs_dr.core.equirect import equirect_directions
from comgs_dr.lighting.envmap import equirect_to_oct_np, write_exr


def _sun_map(h, az_shift=0):
    d = equirect_directions(h, 2 * h)
    img = np.stack([0.2 + 0.1 * d[..., 2]] * 3, -1) + 0.05
    img[h // 4, (h // 2 + az_shift) % (2 * h)] = 400.0                  # a one-pixel sun
    return img


def test_same_map_scores_perfect_and_a_brighter_one_shows_its_power(tmp_path, capsys):
    t = write_exr(tmp_path / "true.exr", _sun_map(32), "equirect")
    same = write_exr(tmp_path / "same.exr", _sun_map(16) * 4 ** 0, "equirect")   # coarser
    assert cli.main(["compare-light", str(t), str(t), "--json", str(tmp_path / "s.json")]) == 0
    m = json.loads((tmp_path / "s.json").read_text())
    assert m["light_angle_deg"] < 1e-6 and m["power_ratio_est_gt"] == 1.0
    assert "+0.0 %" in capsys.readouterr().out
    write_exr(tmp_path / "twice.exr", 2 * _sun_map(32), "equirect")
    assert cli.main(["compare-light", str(tmp_path / "twice.exr"), str(t), "--json",
                     str(tmp_path / "t.json")]) == 0
    assert json.loads((tmp_path / "t.json").read_text())["power_ratio_est_gt"] == 2.0
    # a coarser estimate is compared at its own size; the sun stays where it is
    assert cli.main(["compare-light", str(same), str(t), "--json", str(tmp_path / "c.json"),
                     "--png", str(tmp_path / "c.png")]) == 0
    from PIL import Image
    sheet = np.asarray(Image.open(tmp_path / "c.png").convert("RGB"), np.float64)
    assert sheet.shape[1] > 2 * sheet.shape[0]                  # two 2:1 panels side by side
    half = sheet.shape[1] // 2
    assert np.abs(sheet[:, :half - 2].mean() - sheet[:, half + 2:].mean()) < 10   # same map
    assert json.loads((tmp_path / "c.json").read_text())["light_angle_deg"] < 6.0


def test_octahedral_estimate_and_a_moved_sun(tmp_path, capsys):
    t = write_exr(tmp_path / "true.exr", _sun_map(32), "equirect")
    o = write_exr(tmp_path / "est_oct.exr", equirect_to_oct_np(_sun_map(32), 32), "octahedral")
    assert cli.main(["compare-light", str(o), str(t), "--json", str(tmp_path / "o.json")]) == 0
    assert json.loads((tmp_path / "o.json").read_text())["light_angle_deg"] < 8.0
    moved = write_exr(tmp_path / "moved.exr", _sun_map(32, az_shift=16), "equirect")
    assert cli.main(["compare-light", str(moved), str(t), "--json", str(tmp_path / "m.json")]) == 0
    el = np.radians(90.0 - 8.5 / 32 * 180.0)          # row 8 of 32; moved 90° in azimuth
    expect = np.degrees(np.arccos(np.sin(el) ** 2))
    m = json.loads((tmp_path / "m.json").read_text())
    assert abs(m["light_angle_deg"] - expect) < 1.0
    # both dominant directions are printed (elevation / azimuth) and recorded
    lines = {ln.split(":")[0]: ln.rsplit("  ", 1)[-1] for ln in capsys.readouterr().out.splitlines()
             if ln.startswith("dominant light of the")}
    (el_e, az_e), (el_t, az_t) = (tuple(float(v) for v in lines[f"dominant light of the {k}"]
                                        .split(" / ")) for k in ("estimate", "truth"))
    assert abs(el_e - np.degrees(el)) < 1.0 and abs(el_t - np.degrees(el)) < 1.0
    assert abs((az_t - az_e) % 360.0 - 90.0) < 1.0                 # moved by 16 of 64 columns
    np.testing.assert_allclose(np.degrees(np.arccos(np.dot(m["est_light_direction"],
                                                           m["true_light_direction"]))),
                               m["light_angle_deg"], atol=1e-6)


def test_missing_file_is_a_clear_error(tmp_path, capsys):
    t = write_exr(tmp_path / "true.exr", _sun_map(16), "equirect")
    assert cli.main(["compare-light", str(tmp_path / "nothing.exr"), str(t)]) == 2
    assert "not found" in capsys.readouterr().err
