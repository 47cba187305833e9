"""The GPU path checked, not assumed: the plugin tests under ``cuda_ad_rgb`` and one step-1
run, one step-2 run and one composite frame timed on ``cuda_ad_rgb`` against ``llvm_ad_rgb``
on the same machine (issue: scale past one CPU).

    python benchmarks/gpu_check.py --work /tmp/gpu_check [--variants llvm_ad_rgb cuda_ad_rgb]

Phases (each prints as it goes; the table at the end; ``WORK/gpu_check.json`` holds it all):

1. **inputs**: ``comgs demo --preset tiny`` under llvm_ad_rgb (its dataset, step-1/step-2
   runs and composition are the inputs of the timed runs below);
2. **plugin tests**: every test file that renders through ``mi.render`` or loads a plugin
   (found by grepping tests/ for ``mi.render(``, ``load_dict(`` and ``render_comp``), run
   with ``pytest --mitsuba-variant V`` for each variant: passed / failed / skipped, seconds;
3. **timed stages**, each variant in its own process (``--mitsuba-variant V``): step 1 on the
   demo's scene dataset (``--iterations``), step 2 on a copy of its object run, and
   ``render-comp --res 512`` of one frame of its composition (the first frame includes the
   kernels' compilation: both the first and the second frame's seconds are reported).

A variant Mitsuba lacks, or CUDA without a device, is reported as such (not an error): on a
machine with no GPU the script still runs the llvm column. Dr.Jit traps the timings expose:
host↔device copies inside a loop (NumPy conversions per iteration) show as a CUDA step-1
slower than its kernels suggest; memory growth per iteration as a rising ``s/it`` — both
read from the runs' own ``metrics.jsonl``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PLUGIN_USE = re.compile(r"mi\.render\(|load_dict\(|render_comp\(")


def run(cmd: list, log: Path, env=None) -> tuple[int, float, str]:
    """(return code, seconds, last lines of output) of ``cmd``, its output in ``log``."""
    t = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT,
                            env={**os.environ, **(env or {})}).returncode
    tail = log.read_text(errors="replace").strip().splitlines()[-3:]
    return rc, time.perf_counter() - t, " | ".join(tail)


def variant_available(v: str) -> str | None:
    """None when variant ``v`` can run here, else why not."""
    code = ("import comgs_dr, sys; comgs_dr.set_variant(sys.argv[1])")
    p = subprocess.run([sys.executable, "-c", code, v], capture_output=True, text=True)
    return None if p.returncode == 0 else (p.stderr.strip().splitlines() or ["?"])[-1]


def plugin_test_files() -> list[str]:
    return sorted(str(p.relative_to(ROOT)) for p in (ROOT / "tests").glob("test_*.py")
                  if PLUGIN_USE.search(p.read_text(errors="replace")))


def pytest_counts(text: str) -> dict:
    out = {}
    for n, what in re.findall(r"(\d+) (passed|failed|skipped|error|errors)", text):
        out[what.rstrip("s") if what.startswith("error") else what] = int(n)
    return out


def phase_tests(work: Path, variants: list, res: dict) -> None:
    files = plugin_test_files()
    print(f"plugin tests: {len(files)} files", flush=True)
    for v in variants:
        log = work / f"tests_{v}.log"
        rc, s, _ = run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                        "--mitsuba-variant", v, *files], log)
        counts = pytest_counts(log.read_text(errors="replace"))
        res[v]["tests"] = {"rc": rc, "seconds": round(s, 1), **counts}
        print(f"  {v}: {counts} in {s:.0f} s (rc {rc}; {log})", flush=True)


def frame_seconds(log: Path) -> tuple[float | None, float | None]:
    """(first, median of the rest) frame seconds from render-comp's summary line."""
    m = re.search(r"first ([\d.]+) s \(kernel compilation included\), then ([\d.]+) s/frame",
                  log.read_text(errors="replace"))
    return (float(m[1]), float(m[2])) if m else (None, None)


def phase_stages(work: Path, demo: Path, variants: list, iters: int, res: dict) -> None:
    comgs = [sys.executable, "-m", "comgs_dr.cli"]
    cams = demo / "dataset" / "comp" / "transforms_test.json"
    for v in variants:
        r = res[v]
        s1 = work / f"step1_{v}"
        shutil.rmtree(s1, ignore_errors=True)
        rc, s, tail = run(comgs + ["reconstruct", str(demo / "dataset" / "scene"), "--out",
                                   str(s1), "--scene", "--iterations", str(iters), "--quiet",
                                   "--mitsuba-variant", v], work / f"step1_{v}.log")
        r["step1"] = {"rc": rc, "seconds": round(s, 1), "iterations": iters, "tail": tail}
        obj = work / f"object_{v}"
        shutil.rmtree(obj, ignore_errors=True)
        shutil.copytree(demo / "object_run", obj, ignore=shutil.ignore_patterns("material"))
        rc, s, tail = run(comgs + ["decompose", str(obj), "--iterations", str(iters),
                                   "--quiet", "--mitsuba-variant", v], work / f"step2_{v}.log")
        r["step2"] = {"rc": rc, "seconds": round(s, 1), "iterations": iters, "tail": tail}
        comp = work / f"comp_{v}"
        shutil.rmtree(comp, ignore_errors=True)
        shutil.copytree(demo / "comp", comp, ignore=shutil.ignore_patterns(
            "renders", "metrics_*.json", "render_*.metrics.jsonl", "path_*.json"))
        rc, s, tail = run(comgs + ["render-comp", str(comp), "--cameras", str(cams), "--res",
                                   "512", "--variant", "sop", "--quiet", "--mitsuba-variant", v],
                          work / f"frame_{v}.log")
        first = second = None
        if rc == 0:
            first, second = frame_seconds(work / f"frame_{v}.log")
        r["frame512"] = {"rc": rc, "seconds": round(s, 1), "first": first, "second": second,
                         "tail": tail}
        print(f"  {v}: step 1 {r['step1']['seconds']} s, step 2 {r['step2']['seconds']} s, "
              f"512² frame {first} s (first) / {second} s", flush=True)


def table(res: dict, variants: list) -> str:
    rows = [("plugin tests passed/failed/skipped",
             lambda r: "{passed}/{failed}/{skipped}".format(**{"passed": 0, "failed": 0,
                                                                "skipped": 0, **r["tests"]})
             if "tests" in r else "-"),
            ("plugin tests s", lambda r: r.get("tests", {}).get("seconds", "-")),
            ("step 1 s", lambda r: r.get("step1", {}).get("seconds", "-")),
            ("step 2 s", lambda r: r.get("step2", {}).get("seconds", "-")),
            ("512² frame s (first)", lambda r: r.get("frame512", {}).get("first", "-")),
            ("512² frame s (then)", lambda r: r.get("frame512", {}).get("second", "-"))]
    lines = ["| | " + " | ".join(variants) + (" | llvm / cuda |" if len(variants) == 2 else " |"),
             "|---" * (len(variants) + 1 + (len(variants) == 2)) + "|"]
    for name, get in rows:
        vals = [get(res[v]) if "unavailable" not in res[v] else "n/a" for v in variants]
        ratio = ""
        if len(variants) == 2 and all(isinstance(x, (int, float)) and x for x in vals):
            ratio = f" | {vals[0] / vals[1]:.1f}×"
        elif len(variants) == 2:
            ratio = " | -"
        lines.append(f"| {name} | " + " | ".join(str(x) for x in vals) + ratio + " |")
    for v in variants:
        if "unavailable" in res[v]:
            lines.append(f"\n{v}: not run here ({res[v]['unavailable']})")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="scratch folder")
    ap.add_argument("--variants", nargs="+", default=["llvm_ad_rgb", "cuda_ad_rgb"])
    ap.add_argument("--iterations", type=int, default=300, help="step-1 and step-2 iterations")
    ap.add_argument("--skip-tests", action="store_true", help="only the timed stages")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    res = {v: {} for v in a.variants}
    for v in a.variants:
        why = variant_available(v)
        if why:
            res[v]["unavailable"] = why
            print(f"{v}: not available here: {why}", flush=True)
    ok = [v for v in a.variants if "unavailable" not in res[v]]
    demo = a.work / "demo"
    if not (demo / "comp" / "composition.json").is_file():
        print("inputs: comgs demo --preset tiny (llvm_ad_rgb)", flush=True)
        rc, s, tail = run([sys.executable, "-m", "comgs_dr.cli", "demo", "--preset", "tiny",
                           "--out", str(demo), "--quiet", "--mitsuba-variant", "llvm_ad_rgb"],
                          a.work / "demo.log")
        if rc != 0:
            raise SystemExit(f"gpu_check: the demo failed ({a.work / 'demo.log'}): {tail}")
    if not a.skip_tests:
        phase_tests(a.work, ok, res)
    phase_stages(a.work, demo, ok, a.iterations, res)
    (a.work / "gpu_check.json").write_text(json.dumps(res, indent=1))
    print()
    print(table(res, a.variants))


if __name__ == "__main__":
    main()
