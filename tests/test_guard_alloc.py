"""The guard-page allocator (tests/guard_alloc.py) and a guarded run of the stages' tests.

Under COMGS_GUARD_ALLOC=1 every numpy buffer of ≥ 4 kB ends less than 16 bytes before a
PROT_NONE page, so a Dr.Jit kernel that reads past a numpy array handed to it crashes at
once instead of at random. The guarded run below covers the conversions of the stages that
handle arrays large enough (> 1024 elements) for Dr.Jit's multi-packet kernels.
"""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("numpy_allocator")
TESTS = Path(__file__).parent

_PROBE = textwrap.dedent("""
    import sys
    sys.path.insert(0, sys.argv[1])
    import numpy as np, drjit as dr, mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from guard_alloc import allocator
    from comgs_dr.core.hostarray import to_jit
    with allocator():
        a = np.linspace(0, 1, 100_003, dtype=np.float32)
        end = a.ctypes.data + a.nbytes
        page = end + (-end) % 4096
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
    assert 0 <= int(gap) < 16 and "'---p'" in prot, guard[0]
    assert raw.returncode != 0 and "survived" not in raw.stdout      # caught at once
    ours = _probe("to_jit")
    assert ours.returncode == 0 and "survived" in ours.stdout, ours.stderr[-2000:]
