"""core.hostarray.to_jit: host data -> Dr.Jit arrays that Dr.Jit's kernels cannot read past."""
import subprocess
import sys
import textwrap

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core.hostarray import PAD_ELEMENTS, host_dtype, padded, to_jit

# A float32 array of n elements that ends exactly where an unmapped page begins, then one
# elementwise kernel over it (run in a child process: the failure mode is a segfault).
_EDGE = textwrap.dedent("""
    import ctypes, mmap, sys
    import numpy as np, drjit as dr, mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from comgs_dr.core.hostarray import to_jit
    libc = ctypes.CDLL(None)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                          ctypes.c_int, ctypes.c_long]
    n, how = int(sys.argv[1]), sys.argv[2]
    P = mmap.PAGESIZE
    pages = 4 * n // P + 2
    libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    base = libc.mmap(None, pages * P, 3, mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS, -1, 0)
    assert libc.mprotect(base + (pages - 1) * P, P, 0) == 0      # PROT_NONE, stays reserved
    start = base + (pages - 1) * P - 4 * n
    a = np.ctypeslib.as_array(ctypes.cast(start, ctypes.POINTER(ctypes.c_float)), shape=(n,))
    a[:] = np.linspace(0, 1, n, dtype=np.float32)
    x = mi.Float(a) if how == "raw" else to_jit(mi.Float, a)
    y = dr.sqrt(x + 1.0) * 2.0
    dr.eval(y)
    dr.sync_thread()
    ref = np.sqrt(np.linspace(0, 1, n, dtype=np.float32) + 1) * 2
    assert np.allclose(np.array(y), ref, rtol=1e-6)
    print("ok")
""")


def _edge(n, how):
    return subprocess.run([sys.executable, "-c", _EDGE, str(n), how], capture_output=True,
                          text=True, timeout=120)


def test_to_jit_survives_an_array_that_ends_at_an_unmapped_page():
    """The same host array that makes Dr.Jit's kernel read into an unmapped page (segfault)
    is safe through to_jit. If the raw case stops crashing, Dr.Jit has fixed the over-read
    and hostarray's padding can go."""
    n = 100_003                                   # 3 elements in the last packet: 52 bytes over
    raw = _edge(n, "raw")
    assert raw.returncode != 0, ("Dr.Jit no longer reads past a mapped array: "
                                 "comgs_dr.core.hostarray's padding may be dropped")
    ours = _edge(n, "to_jit")
    assert ours.returncode == 0 and "ok" in ours.stdout, ours.stderr[-2000:]


@pytest.mark.parametrize("name,data", [
    ("Float", np.linspace(-1, 1, 37)),                             # float64 in, float32 out
    ("UInt32", np.arange(40, dtype=np.int64)),
    ("Bool", np.arange(33) % 3 == 0),
    ("Point3f", np.arange(3 * 21, dtype=np.float32).reshape(3, 21)),
    ("TensorXf", np.random.default_rng(0).normal(size=(5, 7, 3))),
])
def test_to_jit_round_trip(name, data):
    cls = getattr(mi, name)
    x = to_jit(cls, data)
    assert type(x) is cls
    back = np.array(x)
    assert back.dtype == host_dtype(cls)
    assert back.shape == data.shape
    np.testing.assert_array_equal(back, data.astype(host_dtype(cls)))


def test_padded_keeps_a_zeroed_packet_after_the_data():
    a = np.arange(10, dtype=np.float32).reshape(2, 5)
    v = padded(a)
    assert v.shape == (2, 5) and v.flags.c_contiguous and not np.shares_memory(v, a)
    tail = v.base[a.size:]                       # the buffer behind the view
    assert tail.size == PAD_ELEMENTS and not tail.any()


def test_the_padded_buffer_lives_as_long_as_the_jit_array():
    import gc
    import weakref
    view = padded(np.arange(5000, dtype=np.float32))
    alive = weakref.ref(view.base)
    x = mi.Float(view)                                # what to_jit does with the view
    del view
    gc.collect()
    assert alive() is not None                        # Dr.Jit holds the buffer
    assert float(dr.sum(x * 2.0)[0]) == 2.0 * sum(range(5000))
    del x
    gc.collect()
    assert alive() is None                            # and releases it


def test_to_jit_accepts_lists_transposes_and_jit_values():
    assert np.array(to_jit(mi.Float, [1.0, 2.0, 3.0])).tolist() == [1.0, 2.0, 3.0]
    a = np.arange(12, dtype=np.float64).reshape(4, 3)
    np.testing.assert_array_equal(np.array(to_jit(mi.Point3f, a.T)), a.T.astype(np.float32))
    assert dr.width(to_jit(mi.Float, np.zeros(0))) == 0
    y = dr.arange(mi.Float, 4)
    assert np.array(to_jit(mi.Float, y)).tolist() == [0, 1, 2, 3]
    dr.enable_grad(y)
    p = to_jit(mi.Point3f, [y, y, y])                 # Dr.Jit components keep their gradients
    assert dr.grad_enabled(p)


def test_to_jit_accepts_cpu_torch_tensors():
    torch = pytest.importorskip("torch")
    t = torch.arange(6, dtype=torch.float64).reshape(2, 3).requires_grad_(True)
    x = to_jit(mi.TensorXf, t)
    assert x.shape == (2, 3) and np.array(x).ravel().tolist() == [0, 1, 2, 3, 4, 5]
