"""Host (numpy) data -> Dr.Jit arrays, with the padding Dr.Jit 1.5's LLVM kernels need.

Dr.Jit maps a C-contiguous CPU ndarray zero-copy (``mi.Float(a)``, ``mi.TensorXf(a)``,
``mi.Point3f(a)``), and its LLVM kernels load the last 16-wide packet of a mapped array
whole: up to 15 elements past the end of the array (measured on Dr.Jit 1.5.0 with
AVX-512: an array of 100 003 floats ending 48 bytes before an unmapped page segfaults, 56
bytes does not; ``tests/test_hostarray.py``). Whether that page is mapped depends on the
heap's history, so the crash is random: large numpy buffers are served by ``mmap``, and
their end falls within 60 bytes of the mapping's end for ≤ 60 of the 4096 possible offsets
(≈ 1.5 %, an estimate; the next page must also be unmapped).

:func:`to_jit` copies the data into a buffer with one spare packet after it and hands Dr.Jit
a view of it (the view keeps the buffer alive). Every numpy -> Dr.Jit conversion in the
package goes through it; ``tests/guard_alloc.py`` finds, on the paths the tests run,
conversions that do not. Hand-written because neither Dr.Jit nor Mitsuba offers a padded
or copying constructor.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

PAD_ELEMENTS = 16          # one packet at the widest vector width (AVX-512, 16 lanes)

_DTYPES = {
    dr.VarType.Bool: np.bool_, dr.VarType.Int8: np.int8, dr.VarType.UInt8: np.uint8,
    dr.VarType.Int16: np.int16, dr.VarType.UInt16: np.uint16, dr.VarType.Int32: np.int32,
    dr.VarType.UInt32: np.uint32, dr.VarType.Int64: np.int64, dr.VarType.UInt64: np.uint64,
    dr.VarType.Float16: np.float16, dr.VarType.Float32: np.float32,
    dr.VarType.Float64: np.float64,
}


def padded(a, dtype=None) -> np.ndarray:
    """A C-contiguous copy of ``a`` (as ``dtype``) followed by PAD_ELEMENTS zeroed spare
    elements in the same buffer; returned as a view of shape ``a.shape``."""
    a = np.asarray(a)
    buf = np.empty(a.size + PAD_ELEMENTS, a.dtype if dtype is None else dtype)   # [size + 16]
    out = buf[:a.size].reshape(a.shape)
    np.copyto(out, a, casting="unsafe")      # one copy, also from transposed views
    buf[a.size:] = 0
    return out


def host_dtype(cls) -> np.dtype:
    """The numpy dtype of a Dr.Jit array type's scalars (``mi.Point3f`` -> float32)."""
    try:
        return np.dtype(_DTYPES[dr.type_v(cls)])
    except KeyError:
        raise TypeError(f"to_jit: no host dtype for Dr.Jit type {cls.__name__}") from None


def to_jit(cls, a):
    """``cls(a)`` for host data ``a`` (numpy array, list, or anything ``np.asarray`` takes,
    including CPU torch tensors), converted to ``cls``'s scalar type and padded by one
    packet; nested types take their components on the first axis (``[3, N]`` for
    ``mi.Point3f``), tensors any shape."""
    if isinstance(a, dr.ArrayBase):
        return cls(a)
    if isinstance(a, (list, tuple)) and any(isinstance(c, dr.ArrayBase) for c in a):
        return cls(*a)                      # Dr.Jit components: no host data, AD kept
    if hasattr(a, "detach") and hasattr(a, "cpu"):          # torch tensor
        a = a.detach().cpu().numpy()
    return cls(padded(a, host_dtype(cls)))
