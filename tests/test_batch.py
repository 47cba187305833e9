"""``comgs batch`` and ``render-comp --ray`` (comgs_dr.batch): the jobs file's errors, frame
shards bit-identical to the single process, a killed worker retried without a frame lost
or written twice, a failing job failing alone. One local Ray instance (2 CPUs) for the
module; a tiny composition (a surfel plane and a ball, 32 px frames)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import pytest

from comgs_dr.batch.spec import JobsFileError, parse_jobs

RAYS = 4


@pytest.fixture(scope="module")
def ray_local():
    ray = pytest.importorskip("ray")
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    if started:
        ray.shutdown()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A scene run (plane), an object run (ball + probes), a sun map, placements, a NeRF
    capture of 4 views (32 px, flat grey: the ground truth of the metrics) and a
    composition of the two (``comp``)."""
    from test_composite import tiny_composition
    return tiny_composition(tmp_path_factory.mktemp("batch"), 32, (("t", 0.2), ("t2", -0.2)))


def _pngs(folder) -> dict:
    return {p.name: p.read_bytes() for p in sorted(Path(folder).glob("*.png"))}


def _fresh_comp(tiny, name) -> Path:
    """A copy of the composition without renders."""
    out = tiny / name
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(tiny / "comp", out, ignore=shutil.ignore_patterns("renders", "metrics_*"))
    return out


# --------------------------------------------------------------------------- the jobs file

def _doc(tiny, **job):
    return {"scenes": {"s": {"run": str(tiny / "scene_run")}},
            "objects": {"a": {"run": str(tiny / "a")}},
            "jobs": [{"name": "j", "scene": "s", "objects": ["a"], "placement": "t.json",
                      "out": "c", "compose": {"env": "env.exr"},
                      "render": {"cameras": "data/transforms_test.json", "res": 32,
                                 "rays": RAYS}, **job}]}


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.pop("jobs"), r"the file: 'jobs' is missing"),
    (lambda d: d.update(job=[]), r"the file: unknown key 'job'"),
    (lambda d: d["jobs"][0].update(scene="t"), r"jobs\[0\] \(j\)\.scene: 't' is not in scenes"),
    (lambda d: d["jobs"][0].update(objects=["b"]), r"jobs\[0\] \(j\)\.objects: 'b' is not in"),
    (lambda d: d["jobs"][0]["render"].update(variant="pbr"),
     r"jobs\[0\] \(j\)\.render\[0\]: render-comp: variant must be one of"),
    (lambda d: d["jobs"][0]["render"].update(shards=0),
     r"jobs\[0\] \(j\)\.render\[0\]\.shards: must be"),
    (lambda d: d["jobs"][0]["compose"].update(label="outdoor"),
     r"jobs\[0\] \(j\)\.compose: label sets up the lighting estimation; with env"),
    (lambda d: d["jobs"][0]["compose"].update(shadow_probes=0),
     r"jobs\[0\] \(j\)\.compose: --shadow-probes must be"),
    (lambda d: d["jobs"].append(dict(d["jobs"][0], name="k")), r"jobs\[1\] \(k\): out .* is "
     r"also j's"),
    (lambda d: d["objects"].update(b={"data": "x", "out": "o", "reconstruct":
                                      {"iterations": 0}}),
     r"objects\.b\.reconstruct: RadianceConfig\.iterations must be ≥ 1"),
    (lambda d: d["objects"].update(b={"data": "x", "out": "o", "decompose": {"rayz": 4}}),
     r"objects\.b\.decompose: unknown key 'rayz'"),
    (lambda d: d["objects"].update(b={"data": "x"}), r"objects\.b: 'out' is missing"),
    (lambda d: d.update(retries=-1), r"retries: must be an integer >= 0"),
])
def test_jobs_file_errors_name_the_file_and_the_entry(tiny, edit, match):
    doc = _doc(tiny)
    edit(doc)
    with pytest.raises(JobsFileError, match=r"jobs\.yaml: " + match):
        parse_jobs(doc, tiny / "jobs.yaml")


def test_jobs_file_paths_and_cli_exit_2(tiny, capsys):
    import yaml

    from comgs_dr.cli import main
    b = parse_jobs(_doc(tiny), tiny / "jobs.yaml")
    j = b.jobs[0]
    assert j.placement == str(tiny / "t.json") and j.out == str(tiny / "c")
    assert j.compose["env"] == str(tiny / "env.exr") and j.objects == {"a": "a"}
    assert j.renders[0].cameras == str(tiny / "data" / "transforms_test.json")
    bad = tiny / "bad.yaml"
    bad.write_text(yaml.safe_dump(_doc(tiny, scene="nowhere")))
    assert main(["batch", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: jobs[0] (j).scene: 'nowhere' is not in scenes" in err
    bad.write_text("jobs: [\n")
    assert main(["batch", str(bad)]) == 2 and "not valid YAML" in capsys.readouterr().err
    assert main(["render-comp", str(tiny / "comp"), "--path", "orbit", "--shards", "2"]) == 2
    assert "give --ray too" in capsys.readouterr().err


# --------------------------------------------------------------------------- shards, no Ray

def test_shards_and_merge_write_the_single_process_bytes_and_metrics(tiny):
    """render_comp's sharding hooks in one process (the code path of every Ray shard): two
    shards (frames 0, 2 and 1, 3) then the merge give the single run's PNGs and metrics; a
    temporary a killed write left is removed; no partial file stays."""
    from comgs_dr.stages.render_comp import render_comp
    cams, gt = tiny / "data" / "transforms_test.json", tiny / "data"
    one, sh = _fresh_comp(tiny, "one"), _fresh_comp(tiny, "sharded")
    m1 = render_comp(one, cams, "sop", gt, rays=RAYS, progress=False)
    out = sh / "renders" / "sop"
    out.mkdir(parents=True)
    (out / "r_1.png.999.dead.tmp").write_bytes(b"partial")      # a killed write's leftover
    done, seen = {}, []
    for k in range(2):
        s = render_comp(sh, cams, "sop", gt, rays=RAYS, progress=False,
                        frame_indices=slice(k, None, 2),
                        on_frame=lambda i, rec: (seen.append(i), done.update({rec["name"]: rec})))
        assert [f["name"] for f in s["per_frame"]] == [f"r_{i}" for i in range(k, 4, 2)]
        assert not (sh / "metrics_sop.json").exists()
    assert sorted(seen) == [0, 1, 2, 3]
    m2 = render_comp(sh, cams, "sop", gt, rays=RAYS, progress=False, done=done,
                     on_frame=lambda i, rec: seen.append(i))
    assert len(seen) == 4                       # the merge renders nothing
    assert _pngs(out) == _pngs(one / "renders" / "sop") and len(_pngs(out)) == 4
    assert not list(out.glob("*.tmp"))
    for a, b in zip(m1["per_frame"], m2["per_frame"]):
        assert (a["name"], a["psnr"], a["ssim"]) == (b["name"], b["psnr"], b["ssim"])
    assert json.loads((sh / "metrics_sop.json").read_text())["psnr"] == m1["psnr"]
    assert len((sh / "render_sop.metrics.jsonl").read_text().splitlines()) == 4


# --------------------------------------------------------------------------- Ray

def test_render_comp_ray_is_bit_identical_to_the_single_process(tiny, ray_local, capsys):
    """16 path frames: `render-comp --ray local --shards 2` writes the single process's
    PNG bytes, and the same metrics with ground truth."""
    from comgs_dr.cli import main
    one, ray_comp = _fresh_comp(tiny, "one16"), _fresh_comp(tiny, "ray16")
    args = ["--path", "orbit", "--frames", "16", "--rays", str(RAYS), "--quiet"]
    assert main(["render-comp", str(one), *args]) == 0
    assert main(["render-comp", str(ray_comp), *args, "--ray", "local", "--shards", "2"]) == 0
    assert "2 shard(s), 0 task(s) retried, 0 frame(s) lost" in capsys.readouterr().err
    a, b = _pngs(one / "renders" / "sop"), _pngs(ray_comp / "renders" / "sop")
    assert len(a) == 16 and a == b
    assert json.loads((ray_comp / "path_sop.json").read_text())["frames"] == 16
    from comgs_dr.batch import render_sharded
    from comgs_dr.batch.spec import Render
    cams, gt = tiny / "data" / "transforms_test.json", tiny / "data"
    from comgs_dr.stages.render_comp import render_comp
    m1 = render_comp(one, cams, "sop", gt, rays=RAYS, progress=False)
    m2 = render_sharded(ray_comp, Render(str(cams), str(gt), 3, {"rays": RAYS}))
    assert m2["psnr"] == m1["psnr"] and m2["ssim"] == m1["ssim"] and m2["lost"] == 0
    assert _pngs(one / "renders" / "sop") == _pngs(ray_comp / "renders" / "sop")


def test_a_killed_worker_is_retried_no_frame_lost_or_written_twice(tiny, ray_local):
    """SIGKILL the worker of shard 0 once it has finished a frame: Ray retries the shard,
    which skips the frames recorded; every frame is there once, bytes as the single
    process's, no temporary left."""
    from comgs_dr.batch import render_sharded
    from comgs_dr.batch.spec import Render
    from comgs_dr.stages.render_comp import render_comp
    one, comp = _fresh_comp(tiny, "one_kill"), _fresh_comp(tiny, "kill")
    settings = {"path": "orbit", "frames": 12, "rays": 64}
    render_comp(one, None, "sop", rays=64, progress=False, path="orbit", frames=12)
    work = tiny / "kill_work"
    label = "render-comp-sop"
    result, killed = {}, []
    th = threading.Thread(target=lambda: result.update(s=render_sharded(
        comp, Render(None, None, 2, settings), work=work)))
    th.start()
    attempts = work / "attempts" / f"{label}.shard0of2"
    records = work / "records" / label
    deadline = time.time() + 120
    while time.time() < deadline and th.is_alive() and not killed:
        if (records / "path_0000.json").exists() and attempts.is_dir():
            pid = json.loads(next(attempts.glob("*.json")).read_text())["pid"]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
        time.sleep(0.01)
    th.join(300)
    assert killed and not th.is_alive()
    s = result["s"]
    assert s["attempts"][f"{label}.shard0of2"] == 2          # retried once
    assert s["attempts"][f"{label}.shard1of2"] == 1
    assert s["lost"] == 0 and s["partial_files"] == 0 and s["frames_rendered_twice"] == 0
    assert s["rendered_in_merge"] == [] and s["resumed_frames"] >= 1   # not re-rendered
    out = comp / "renders" / "sop"
    assert _pngs(out) == _pngs(one / "renders" / "sop") and len(_pngs(out)) == 12
    assert not list(out.glob("*.tmp"))


def test_batch_runs_the_graph_and_a_bad_job_fails_alone(tiny, ray_local, capsys):
    """Three jobs sharing one object: the good one composes and renders (2 shards); one
    with a missing placement fails in its compose; one whose object cannot be reconstructed
    (no dataset) fails with that error; the object reconstructed once for two jobs."""
    import yaml

    from comgs_dr.cli import main
    doc = _doc(tiny)
    doc["objects"]["broken"] = {"data": "no_such_dataset", "out": "runs/broken"}
    good = doc["jobs"][0]
    good["render"]["shards"] = 2
    doc["jobs"] += [dict(good, name="noplace", placement="missing.json", out="c2"),
                    dict(good, name="nobject", objects={"a": "broken"}, out="c3"),
                    dict(good, name="again", objects={"a": "broken"}, out="c4",
                         placement="t2.json"),
                    {"name": "old", "comp": str(_fresh_comp(tiny, "old")),     # render only
                     "render": {"path": "orbit", "frames": 3, "rays": RAYS, "shards": 2}}]
    path = tiny / "jobs.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert main(["batch", str(path), "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "j: ok" in out and "noplace: FAILED in job-noplace.compose: FileNotFoundError" in out
    assert "nobject: FAILED in object-broken.reconstruct" in out
    s = json.loads((tiny / "jobs.batch" / "summary.json").read_text())
    assert (s["jobs_ok"], s["jobs_failed"]) == (2, 3)
    assert sum(k.endswith(".reconstruct") for k in s["attempts"]) == 1   # once, 2 jobs
    assert s["retried_tasks"] == 0 and s["frames"] == 7 and s["frames_lost"] == 0
    assert len(_pngs(tiny / "old" / "renders" / "sop")) == 3
    assert json.loads((tiny / "old" / "path_sop.json").read_text())["frames"] == 3
    assert "no_such_dataset" in {j["name"]: j for j in s["jobs"]}["again"]["error"]
    assert len(_pngs(tiny / "c" / "renders" / "sop")) == 4
    assert (tiny / "c" / "composition.json").is_file() and not (tiny / "c2").exists()


@pytest.mark.slow
def test_batch_reconstructs_decomposes_composes_and_renders(tmp_path, ray_local):
    """The whole graph from datasets (the tiny demo's, a few iterations): scene and object
    reconstructed, the object decomposed, composed under the sky map, rendered in 2 shards
    with ground truth; the outputs where the single commands write them. (The fast tests
    run the same graph from existing runs.)"""
    import dataclasses

    import yaml

    from comgs_dr.batch import load_jobs, run_batch
    from comgs_dr.demo import PRESETS, _ground_truth
    (tmp_path / "inputs").mkdir()
    ds, _ = _ground_truth(dataclasses.replace(PRESETS["tiny"], progress=False), tmp_path)
    quick = {"iterations": 2, "eval_every": 1, "eval_views": 1}
    doc = {"scenes": {"yard": {"data": str(ds / "scene"), "out": "runs/yard",
                               "reconstruct": quick}},
           "objects": {"torus": {"data": str(ds / "objects" / "torus"), "out": "runs/torus",
                                 "reconstruct": quick,
                                 "decompose": {**quick, "iterations": 1, "probe_count": 20,
                                               "rays": 4, "env_res": 16}}},
           "jobs": [{"name": "a", "scene": "yard", "objects": ["torus"],
                     "placement": str(ds / "transform.json"), "out": "comps/a",
                     "compose": {"preset": "fast", "shadow_probes": 50, "env_res": 16,
                                 "env": str(tmp_path / "inputs" / "sky.exr"),
                                 "scene_views": 4, "min_consistent": 1},
                     "render": {"cameras": str(ds / "comp" / "transforms_test.json"),
                                "gt_dir": str(ds / "comp" / "gt"), "rays": 4, "shards": 2}}]}
    (tmp_path / "jobs.yaml").write_text(yaml.safe_dump(doc))
    s = run_batch(load_jobs(tmp_path / "jobs.yaml"), say=lambda *a: None)
    assert s["jobs_ok"] == 1, s["task_errors"]
    assert s["tasks"] == 7 and s["frames"] == 2 and s["frames_lost"] == 0
    assert (tmp_path / "runs" / "yard" / "point_cloud.ply").is_file()
    assert (tmp_path / "runs" / "torus" / "material").is_dir()
    comp = tmp_path / "comps" / "a"
    assert (comp / "composition.json").is_file() and (comp / "metrics_sop.json").is_file()
    assert len(_pngs(comp / "renders" / "sop")) == 2
