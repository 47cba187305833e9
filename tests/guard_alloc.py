"""Guard-page allocator for numpy: finds code that hands Dr.Jit unpadded host memory.

Dr.Jit 1.5's LLVM backend maps a CPU ndarray zero-copy (``mi.Float(a)``, ``mi.TensorXf(a)``)
and its kernels over more than 1024 elements read the whole last 16-wide packet of the
mapped array: up to 15 elements past its end (``tests/test_hostarray.py``). When the array
ends just before an unmapped page the process segfaults, at random, depending on the heap.

With ``COMGS_GUARD_ALLOC=1`` the test session allocates every numpy buffer of at least
``MIN_BYTES`` so that it ends exactly at a ``PROT_NONE`` page (Electric-Fence style), which
turns such a read into a deterministic crash at the offending kernel. Only the main
thread's numpy allocations are guarded (numpy's handler is a context variable), and
notebooks run in their own kernels, unguarded.

The allocator is a few lines of C compiled with the system's ``cc`` on first use (cached in
the temp folder) and installed with the ``numpy-allocator`` package: Python callbacks would
run while numpy frees arrays during exception unwinding, which CPython does not allow.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

MIN_BYTES = 4096           # 1024 float32: smaller kernels do not over-read (measured)

_SOURCE = r"""
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>
#define MIN_BYTES %(min_bytes)d
#define MAGIC_GUARD 0x6775617264706167ULL
#define MAGIC_SMALL 0x736d616c6c626c6bULL
typedef struct { uint64_t magic, base, length, size; } hdr_t;   /* 32 bytes before the data */

void *guard_malloc(size_t size) {
    if (size < MIN_BYTES) {
        char *p = malloc(size + sizeof(hdr_t));
        if (!p) return NULL;
        hdr_t *h = (hdr_t *) p;
        h->magic = MAGIC_SMALL; h->size = size;
        return p + sizeof(hdr_t);
    }
    size_t page = (size_t) sysconf(_SC_PAGESIZE);
    size_t pages = (size + 64 + page - 1) / page, length = (pages + 1) * page;
    char *base = mmap(NULL, length, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (base == MAP_FAILED) return NULL;
    char *guard = base + pages * page;
    if (mprotect(guard, page, PROT_NONE) != 0) abort();
    /* the data end exactly at the guard page; the start is then aligned to size's lowest set
       bit, at least the element size of the array numpy asked for */
    char *ptr = guard - size;
    hdr_t *h = (hdr_t *) (ptr - sizeof(hdr_t));
    h->magic = MAGIC_GUARD; h->base = (uint64_t) base; h->length = length; h->size = size;
    return ptr;
}

void guard_free(void *ptr) {
    if (!ptr) return;
    hdr_t *h = (hdr_t *) ((char *) ptr - sizeof(hdr_t));
    if (h->magic == MAGIC_GUARD) { h->magic = 0; munmap((void *) h->base, h->length); }
    else if (h->magic == MAGIC_SMALL) { h->magic = 0; free(h); }
    else abort();                                    /* not ours: fail loudly */
}

void *guard_calloc(size_t n, size_t size) {
    if (size && n > SIZE_MAX / size) return NULL;
    void *p = guard_malloc(n * size);
    if (p && n * size < MIN_BYTES) memset(p, 0, n * size);   /* mmap pages are zeroed */
    return p;
}

void *guard_realloc(void *ptr, size_t size) {
    if (!ptr) return guard_malloc(size);
    hdr_t *h = (hdr_t *) ((char *) ptr - sizeof(hdr_t));
    void *q = guard_malloc(size);
    if (!q) return NULL;
    memcpy(q, ptr, h->size < size ? h->size : size);
    guard_free(ptr);
    return q;
}
"""


def compiler() -> str | None:
    return shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")


def _library() -> ctypes.CDLL:
    src = _SOURCE % {"min_bytes": MIN_BYTES}
    tag = hashlib.sha1(src.encode()).hexdigest()[:12]
    folder = Path(tempfile.gettempdir()) / f"comgs_guard_alloc_{os.getuid()}"
    folder.mkdir(mode=0o700, exist_ok=True)
    lib = folder / f"guard_{tag}.so"
    if not lib.exists():
        cc = compiler()
        if cc is None:
            raise RuntimeError("guard_alloc: no C compiler (cc) to build the allocator")
        with tempfile.TemporaryDirectory(dir=folder) as tmp:     # private names: no races
            c_file, so_file = Path(tmp) / "guard.c", Path(tmp) / "guard.so"
            c_file.write_text(src)
            subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", str(so_file), str(c_file)],
                           check=True)
            os.replace(so_file, lib)
    return ctypes.CDLL(str(lib))


def allocator():
    """The numpy-allocator handler (use as a context manager)."""
    import numpy_allocator
    lib = _library()

    class guard_pages(metaclass=numpy_allocator.type):
        _malloc_ = ctypes.addressof(lib.guard_malloc)
        _calloc_ = ctypes.addressof(lib.guard_calloc)
        _realloc_ = ctypes.addressof(lib.guard_realloc)
        _free_ = ctypes.addressof(lib.guard_free)
    for obj in (guard_pages, lib, lib.guard_malloc, lib.guard_calloc, lib.guard_realloc,
                lib.guard_free):
        ctypes.pythonapi.Py_IncRef(ctypes.py_object(obj))   # numpy reads the pointers through
    return guard_pages                                      # these until the process ends
