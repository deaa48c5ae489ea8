"""How a process that repeats the same work every frame allocates memory: it keeps what it freed.

glibc's malloc serves large blocks (from 128 KB, a threshold that adapts up
to 32 MB) with fresh pages from the kernel and gives freed memory back, so
every frame's tensors and multi-megabyte messages are zero-filled and
page-faulted anew, in a virtual machine at well under a gigabyte a second:
a quarter of the LiDAR vehicle half's time in float32 on one thread, and two
thirds of what a 3 MB message costs its subscriber (BENCHMARKS.md, "Memory
the process keeps").
Raising both thresholds lets freed blocks serve the next frame; the process
then holds on to its peak, which a node reaches in its first frame anyway
(`CO3SOP_KEEP_FREED_MEMORY=0` in the environment leaves malloc as it is).
The Python side: objects that live as long as the process (modules, the
model) are moved out of the garbage collector's reach once set up, so its
full collections stop walking them on every frame.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
from functools import cache

# blocks up to this size come from the heap; the heap's free top is given back beyond the trim threshold
MMAP_THRESHOLD = 64 << 20
TRIM_THRESHOLD = 256 << 20
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt's parameters (malloc.h)


@cache
def keep_freed_memory() -> bool:
    """Raises glibc malloc's mmap and trim thresholds for this process (once); False where the C library is not
    glibc (nothing to change there) or the environment says CO3SOP_KEEP_FREED_MEMORY=0."""
    if os.environ.get("CO3SOP_KEEP_FREED_MEMORY", "1") == "0":
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))


def freeze_setup() -> None:
    """Moves every object alive now (modules, a loaded model, compiled kernels) out of the garbage collector's
    generations, after a collection: later collections walk only what frames allocate."""
    gc.collect()
    gc.freeze()
