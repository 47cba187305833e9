"""The (time, metric) log format, the HTML report and the demo that writes it."""
import base64
import io
import json
import math
import re

import numpy as np
import pytest
from PIL import Image

from comgs_dr.core import runlog


def inlined_images(html_text: str) -> list[Image.Image]:
    """Every <img> of the report, decoded; fails on any image that is not an inlined PNG."""
    srcs = re.findall(r'<img[^>]*\bsrc="([^"]*)"', html_text)
    assert len(srcs) == html_text.count("<img"), "an <img> without a src"
    out = []
    for s in srcs:
        assert s.startswith("data:image/png;base64,"), f"not inlined: {s[:60]}"
        im = Image.open(io.BytesIO(base64.b64decode(s.split(",", 1)[1], validate=True)))
        im.load()                                   # decodes the whole PNG
        assert im.width > 0 and im.height > 0
        out.append(im)
    # nothing else is fetched: no external scripts, styles or links
    assert not re.search(r'<(script|link)\b', html_text)
    assert not re.search(r'\b(href|src)="(?!data:)', html_text)
    return out


def test_runlog_roundtrip_torn_line_and_errors(tmp_path):
    runlog.rewrite(tmp_path, [runlog.record("s", 0.5, iteration=1, psnr=np.float32(20.5))])
    runlog.append(tmp_path, runlog.record("s", 1.0, iteration=2, loss=float("nan"),
                                          arr=np.zeros(3)))
    with open(tmp_path / runlog.LOG_NAME, "a") as f:
        f.write('{"stage": "s", "time_')              # a writer killed mid-line
    recs = runlog.read_records(tmp_path / runlog.LOG_NAME)
    assert [r["iteration"] for r in recs] == [1, 2]
    assert recs[0]["psnr"] == pytest.approx(20.5) and recs[1]["loss"] is None   # NaN -> null
    assert "arr" not in recs[1]                                   # only scalars are logged
    runlog.rewrite(tmp_path, [])                                   # atomic replace
    assert runlog.read_records(tmp_path / runlog.LOG_NAME) == []
    (tmp_path / "bad.metrics.jsonl").write_text('{"time_s": 1}\n')
    with pytest.raises(ValueError, match="bad.metrics.jsonl:1"):
        runlog.read_records(tmp_path / "bad.metrics.jsonl")


def test_json_safe_gives_strict_json():
    x = {1: (np.float32(2.5), np.array([1.0, np.inf])), "n": float("nan"), "s": "a",
         "i": np.int64(3), "b": True, "z": None}
    y = runlog.json_safe(x)
    assert y == {"1": [2.5, [1.0, None]], "n": None, "s": "a", "i": 3, "b": True, "z": None}
    assert json.loads(json.dumps(y, allow_nan=False)) == y
    assert math.isnan(x["n"])                                     # the input is not modified


def test_train_loop_writes_jsonl_and_resume_drops_stale(tmp_path):
    from comgs_dr.train.loop import run_loop

    class Cfg:
        iterations, log_every, eval_every, eval_views, checkpoint_every, time_limit_s = 6, 1, 3, 1, 100, None

    class T:
        def __init__(self, log=()):
            self.iteration, self.elapsed, self.log = 0, 0.0, list(log)

        def step(self):
            self.iteration += 1
            return {"loss": 1.0 / self.iteration, "psnr_train": 10.0 + self.iteration}

        def evaluate(self, n):
            return {"psnr_test": 9.0 + self.iteration}

        def checkpoint(self):
            pass

    t = T()
    run_loop(t, Cfg, "x", progress=False, jsonl_dir=tmp_path, stage="reconstruct")
    recs = runlog.read_records(tmp_path / runlog.LOG_NAME)
    assert [r["iteration"] for r in recs] == [1, 2, 3, 4, 5, 6]
    assert all(r["stage"] == "reconstruct" for r in recs)
    assert [r["psnr_test"] for r in recs if "psnr_test" in r] == [12.0, 15.0]
    # a resumed trainer (checkpoint at iteration 2) rewrites the log from its own records
    t2 = T(t.log[:2])
    t2.iteration = 2
    run_loop(t2, Cfg, "x", progress=False, jsonl_dir=tmp_path, stage="reconstruct")
    assert [r["iteration"] for r in runlog.read_records(tmp_path / runlog.LOG_NAME)] == \
        [1, 2, 3, 4, 5, 6]


def test_report_of_a_folder_inlines_and_decodes_everything(tmp_path):
    from comgs_dr.eval.report import load_logs, write_report
    run = tmp_path / "run"
    runlog.rewrite(run, [runlog.record("reconstruct", t, iteration=i, psnr_train=20 + i,
                                       **({"psnr_test": 19 + i} if i % 2 else {}))
                         for i, t in enumerate(np.linspace(0.1, 5, 8))])
    runlog.rewrite(run / "comp", [runlog.record("compose", 1.0, part="lighting", part_s=1.0),
                                  runlog.record("compose", 3.0, part="occlusion", part_s=2.0)])
    runlog.rewrite(run, [runlog.record("train-completion", t, val_ev0=1 / (1 + t))
                         for t in range(5)], name="w.metrics.jsonl")
    (run / "comp" / "renders" / "sop").mkdir(parents=True)
    for i in range(3):
        Image.fromarray((np.random.default_rng(i).random((16, 20, 3)) * 255).astype(np.uint8)
                        ).save(run / "comp" / "renders" / "sop" / f"r_{i}.png")
    (run / "comp" / "metrics_sop.json").write_text(json.dumps(
        {"psnr": 25.0, "ssim": 0.8, "frame_seconds": 0.1, "frames": 3}))
    logs = load_logs(run)
    assert list(logs)[0].startswith("reconstruct") and len(logs) == 3
    out = write_report(run, tmp_path / "r.html", title="T <&>")
    text = out.read_text()
    imgs = inlined_images(text)
    assert len(imgs) == 2                            # the renders strip and the plot panel
    assert imgs[0].size == (60, 16)                  # 3 frames side by side
    assert "T &lt;&amp;&gt;" in text and "metrics_sop.json" in text
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="nothing to report"):
        write_report(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="not a folder"):
        write_report(tmp_path / "missing")


def test_report_cli(tmp_path, capsys):
    from comgs_dr import cli
    runlog.rewrite(tmp_path, [runlog.record("decompose", 1.0, psnr_test=20.0)])
    assert cli.main(["report", str(tmp_path)]) == 0
    inlined_images((tmp_path / "report.html").read_text())
    assert cli.main(["report", str(tmp_path / "nope")]) == 2
    assert "not a folder" in capsys.readouterr().err


def test_compare_maps_identity_rotation_and_irradiance():
    from comgs_dr.eval.lighting_metrics import compare_maps, irradiance
    h, w = 32, 64
    env = np.full((h, w, 3), 0.5)
    assert irradiance(np.ones((h, w, 3)), [0, 0, 1]) == pytest.approx(math.pi, rel=2e-3)
    env[10:12, 40:42] = 500.0                       # a sun
    same = compare_maps(env, env)
    assert same["spheres"]["diffuse"]["si_rmse"] == pytest.approx(0.0, abs=1e-9)
    assert same["light_angle_deg"] == pytest.approx(0.0, abs=1e-6)
    assert same["light_up_irradiance_ratio_est"] == pytest.approx(
        same["light_up_irradiance_ratio_gt"])
    assert same["power_ratio_est_gt"] == pytest.approx(1.0)
    rolled = compare_maps(np.roll(env, w // 4, axis=1), env)      # sun moved by 90 deg azimuth
    assert rolled["light_angle_deg"] == pytest.approx(90 * np.sin(np.radians(180 * 11 / h)),
                                                      abs=12)
    assert rolled["spheres"]["diffuse"]["si_rmse"] > 0.01
    with pytest.raises(ValueError, match="NaN"):
        compare_maps(np.full((h, w, 3), np.nan), env)


def test_demo_tiny_end_to_end_report(tmp_path, capsys):
    """`comgs demo --preset tiny`: every stage runs, logs its records, and the report inlines
    the comparison, the maps, the estimate preview and the error-vs-time plots."""
    from comgs_dr import cli
    out = tmp_path / "demo"
    assert cli.main(["demo", "--preset", "tiny", "--out", str(out), "--quiet"]) == 0
    s = json.loads((out / "demo.json").read_text())
    assert set(s["composition"]) == {"sop", "trace", "paste"}
    for v in s["composition"].values():
        assert math.isfinite(v["psnr"]) and 0 < v["ssim"] <= 1
    assert math.isfinite(s["lighting"]["spheres"]["diffuse"]["si_rmse"])
    sop = s["region"]["sop"]                         # what a user looks at, scored
    assert math.isfinite(sop["psnr_region"]) and len(sop["object_colour_ratio"]) == 3
    assert (out / "crops.png").is_file()
    frame = Image.open(out / "comp" / "renders" / "sop" / "r_000.png")
    assert frame.size == (32, 32)                    # composites at their own size (captures 24)
    stages = {r["stage"] for p in out.rglob("*metrics.jsonl") for r in runlog.read_records(p)}
    assert {"demo", "reconstruct", "decompose", "estimate-light", "compose",
            "render-comp sop", "render-comp trace", "render-comp paste"} <= stages
    text = (out / "report.html").read_text()
    imgs = inlined_images(text)
    assert len(imgs) >= 4                            # comparison, maps, preview, plots
    for caption in ("ground truth | ours (SOP) | ours (trace) | naive paste",
                    "environment map: true | estimated", "Error against run time",
                    "full size, the frame with the most shadow", "Where the object was inserted",
                    "sun from the scene&#x27;s shadows"):
        assert caption in text
    assert "report:" in capsys.readouterr().out


def test_report_shows_a_camera_paths_first_frame_and_links_its_video(tmp_path):
    from comgs_dr.eval.report import build_report
    comp = tmp_path / "comp"
    frames = comp / "renders" / "sop"
    frames.mkdir(parents=True)
    for i, v in enumerate((40, 200)):
        Image.fromarray(np.full((8, 12, 3), v, np.uint8)).save(frames / f"path_{i:04d}.png")
    (tmp_path / "orbit.mp4").write_bytes(b"\0" * 2048)
    (comp / "path_sop.json").write_text(json.dumps({
        "variant": "sop", "path": "orbit", "renders": str(frames), "frame_seconds": 0.5,
        "resolution": [12, 8], "per_frame": [{"name": "path_0000"}, {"name": "path_0001"}],
        "video": str(tmp_path / "orbit.mp4"), "video_bytes": 2048,
        "metrics": "skipped: path frames have no ground truth"}))
    text = build_report(tmp_path)
    assert "Camera path sop" in text and "<a href='orbit.mp4'>" in text
    first = [im for im in inlined_images(text) if im.size == (12, 8)]
    assert first and np.asarray(first[0].convert("RGB")).mean() == pytest.approx(40, abs=1)
