"""Guard-page allocator for numpy: finds code that hands Dr.Jit unpadded host memory.

Dr.Jit 1.5's LLVM backend maps a CPU ndarray zero-copy (``mi.Float(a)``, ``mi.TensorXf(a)``)
and its kernels then read the whole last 16-wide packet of the mapped array: up to 15
elements past its end (measured: ``tests/test_hostarray.py``). When the array ends just
before an unmapped page the process segfaults, at random, depending on the heap layout.

With ``COMGS_GUARD_ALLOC=1`` the test session allocates every numpy buffer of at least
``MIN_BYTES`` so that it ends at most 15 bytes before a ``PROT_NONE`` page (Electric-Fence
style), which turns such a read into a deterministic crash at the offending kernel.
Needs the optional ``numpy-allocator`` package; a diagnostic, not part of the default run.
"""
from __future__ import annotations

import ctypes
import mmap

PAGE = mmap.PAGESIZE
MIN_BYTES = 4096

_libc = ctypes.CDLL(None, use_errno=True)
_libc.mmap.restype = ctypes.c_void_p
_libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                       ctypes.c_int, ctypes.c_long]
_libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
_libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
_libc.malloc.restype = ctypes.c_void_p
_libc.malloc.argtypes = [ctypes.c_size_t]
_libc.calloc.restype = ctypes.c_void_p
_libc.calloc.argtypes = [ctypes.c_size_t, ctypes.c_size_t]
_libc.realloc.restype = ctypes.c_void_p
_libc.realloc.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
_libc.free.argtypes = [ctypes.c_void_p]

_live: dict[int, tuple[int, int, int]] = {}      # data pointer -> (mapping, length, size)
_small: dict[int, int] = {}                        # libc blocks -> size
foreign = [0]                                      # frees of pointers this allocator did not make


def _guarded(size: int) -> int:
    pages = (size + PAGE - 1) // PAGE
    length = (pages + 1) * PAGE
    base = _libc.mmap(None, length, mmap.PROT_READ | mmap.PROT_WRITE,
                      mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS, -1, 0)
    if base in (None, ctypes.c_void_p(-1).value):
        return 0
    guard = base + pages * PAGE
    _libc.mprotect(guard, PAGE, 0)                     # PROT_NONE
    ptr = (guard - size) & ~15                       # 16-byte aligned, ends < 16 bytes before the guard
    _live[ptr] = (base, length, size)
    return ptr


def _small_block(ptr, size):
    if ptr:
        _small[ptr] = size
    return ptr or 0


def _malloc(size):
    return _guarded(size) if size >= MIN_BYTES else _small_block(_libc.malloc(max(size, 1)), size)


def _calloc(n, size):
    total = n * size
    return _guarded(total) if total >= MIN_BYTES else _small_block(_libc.calloc(max(total, 1), 1), total)


def _free(ptr, *_):
    if not ptr:
        return
    entry = _live.pop(ptr, None)
    if entry is not None:
        _libc.munmap(entry[0], entry[1])
    elif _small.pop(ptr, None) is not None:
        _libc.free(ptr)
    else:
        foreign[0] += 1


def _realloc(ptr, size):
    if not ptr:
        return _malloc(size)
    entry = _live.get(ptr)
    old = entry[2] if entry is not None else _small.get(ptr)
    if old is None:
        foreign[0] += 1
        return 0
    new = _malloc(size)
    if new:
        ctypes.memmove(new, ptr, min(old, size))
        _free(ptr)
    return new


_MALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_size_t)(_malloc)
_CALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_size_t, ctypes.c_size_t)(_calloc)
_REALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)(_realloc)
_FREE = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_size_t)(_free)


def allocator():
    """The numpy-allocator handler (use as a context manager)."""
    import numpy_allocator

    class guard_pages(metaclass=numpy_allocator.type):
        _malloc_ = ctypes.addressof(_MALLOC)
        _calloc_ = ctypes.addressof(_CALLOC)
        _realloc_ = ctypes.addressof(_REALLOC)
        _free_ = ctypes.addressof(_FREE)
    return guard_pages
