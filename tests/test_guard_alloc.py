"""The guard-page allocator (tests/guard_alloc.py) and a guarded run of the stages' tests.

Under COMGS_GUARD_ALLOC=1 every numpy buffer of ≥ 4 kB ends exactly at a PROT_NONE page,
so a Dr.Jit kernel that reads past a numpy array handed to it crashes at once instead of
at random. The guarded run below covers the conversions of the stages that handle arrays
large enough (> 1024 elements) for Dr.Jit's multi-packet kernels.
"""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("numpy_allocator")
TESTS = Path(__file__).parent
sys.path.insert(0, str(TESTS))
from guard_alloc import compiler  # noqa: E402

if compiler() is None:
    pytest.skip("no C compiler to build the guard allocator", allow_module_level=True)

_PROBE = textwrap.dedent("""
    import mmap, sys
    sys.path.insert(0, sys.argv[1])
    import numpy as np, drjit as dr, mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from guard_alloc import allocator
    from comgs_dr.core.hostarray import to_jit
    with allocator():
        a = np.linspace(0, 1, 100_003, dtype=np.float32)
        end = a.ctypes.data + a.nbytes
        page = end + (-end) % mmap.PAGESIZE
        maps = open("/proc/self/maps").read().splitlines()
        prot = [m.split()[1] for m in maps
                if int(m.split()[0].split("-")[0], 16) <= page < int(m.split()[0].split("-")[1], 16)]
        print("guard", page - end, prot, flush=True)
        x = mi.Float(a) if sys.argv[2] == "raw" else to_jit(mi.Float, a)
        y = dr.sqrt(x + 1.0)
        dr.eval(y)
        dr.sync_thread()
        print("survived", flush=True)
""")


def _probe(how):
    return subprocess.run([sys.executable, "-c", _PROBE, str(TESTS), how], capture_output=True,
                          text=True, timeout=120)


def test_guard_allocator_ends_buffers_at_a_protected_page():
    raw = _probe("raw")
    guard = [l for l in raw.stdout.splitlines() if l.startswith("guard")]
    assert guard, raw.stderr[-2000:]
    gap, prot = guard[0].split(" ", 2)[1:]
    assert int(gap) == 0 and "'---p'" in prot, guard[0]
    assert raw.returncode != 0 and "survived" not in raw.stdout      # caught at once
    ours = _probe("to_jit")
    assert ours.returncode == 0 and "survived" in ours.stdout, ours.stderr[-2000:]


# Stage tests whose arrays exceed 1024 elements (images, panoramas, probe atlases, rays);
# the whole suite passes guarded too (README, "Tests and benchmarks"), in ~4.5 min.
GUARDED = ["test_composition_dataset.py", "test_raster.py", "test_gbuffer_grad.py",
           "test_sop_query.py", "test_sop_pbr.py", "test_envmap.py", "test_pano_data.py",
           "test_octenvmap.py", "test_placement_probe.py", "test_composite.py",
           "test_background_training.py"]     # runs without the shared data (CI's clones)


def test_stage_tests_pass_with_every_numpy_buffer_at_a_guard_page():
    env = dict(os.environ, COMGS_GUARD_ALLOC="1")
    env.pop("PYTEST_ADDOPTS", None)
    r = subprocess.run([sys.executable, "-X", "faulthandler", "-m", "pytest", "-q",
                        "-p", "no:cacheprovider", *[str(TESTS / f) for f in GUARDED]],
                       cwd=TESTS.parent, env=env, capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0 and " passed" in r.stdout, (r.stdout[-3000:], r.stderr[-3000:])
