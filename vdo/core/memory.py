"""Keep freed memory in the process heap, so that repeated XLA:CPU calls do not fault pages in.

XLA:CPU takes each call's temporary buffer from malloc: 57 MB for the score's value and gradient
on 10 cameras x 100k samples (132 MB before the work ran in chunks). glibc serves a request that
large with a fresh `mmap` and returns it with `munmap` when it is freed, so every call faults in
its pages again: 14,000 per call, 49 ms of kernel time on the 2-core CI machine (32,000 and
88 ms before the chunks), as much as the computation itself (`benchmarks/README.md`,
"Predicted uncertainty").

`retain_freed_memory` sets three glibc malloc options (`mallopt`): one arena for all threads
(M_ARENA_MAX = 1; a thread arena cannot hold a block larger than 64 MB, so it would map it),
no `mmap` for large blocks (M_MMAP_MAX = 0) and no trimming of the heap's free top
(M_TRIM_THRESHOLD maximal). The process then keeps its peak heap and reuses it. Call it before
the first JAX computation: threads that allocated before keep their own arenas. `vdo.core.configure`
calls it (so the command line, the tests and `benchmarks/` do); a no-op where the C
library is not glibc.

`release_freed_memory` is its counterpart for work on large images whose buffers the next work
does not reuse: glibc's `malloc_trim(0)` gives the heap's free pages back. Without it the
retained heap of the built-in's full-size virtual test grew from 2.6 to 8.9 GB over its 24
correlations of 24-megapixel images (fragments of freed images that no later request fit), with
5 MB held by Python objects (`vdo.dic.series.correlate_points` calls it).
"""

from __future__ import annotations

import ctypes
import ctypes.util

_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8  # glibc <malloc.h>


def retain_freed_memory() -> bool:
    """Apply the malloc options above; True when the C library accepted all three."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    settings = ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2 ** 31 - 1))
    return all(mallopt(option, value) == 1 for option, value in settings)


def release_freed_memory() -> bool:
    """Return the heap's free pages to the system (glibc `malloc_trim(0)`, module docstring);
    True where the C library has it."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return False
    trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
    trim(0)
    return True
