"""How a process that repeats the same work every frame allocates memory: it keeps what it freed.

glibc's malloc serves large blocks (from 128 KB, a threshold that adapts up
to 32 MB) with fresh pages from the kernel and gives freed memory back, so
every frame's tensors and multi-megabyte messages are zero-filled and
page-faulted anew, in a virtual machine at well under a gigabyte a second:
a quarter of the LiDAR vehicle half's time in float32 on one thread, and two
thirds of what a 3 MB message costs its subscriber (BENCHMARKS.md, "Memory
the process keeps").
Raising both thresholds lets freed blocks serve the next frame, and one
arena for every thread lets what one thread freed (the executor's messages,
DDS's buffers, the worker's tensors) serve the others. The process then
holds on to its peak. A node would reach it over its first frames, the
graph's busiest, where the ego's first three took three times a later
frame's CPU: nodes reserve memory when they configure (`reserve_memory`),
pages written once and freed, which frames then take without a fault
(BENCHMARKS.md, "Memory reserved at configure").
`CO3SOP_KEEP_FREED_MEMORY=0` in the environment leaves malloc as it is.
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
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8  # mallopt's parameters (malloc.h)
# a reserve is written and freed in blocks this size, served from the heap (below the mmap threshold)
_RESERVE_BLOCK = 16 << 20
# mallopt takes an int: the trim threshold, raised by a reserve, stays below 2 GB
MAX_RESERVE = (1 << 31) - 1 - TRIM_THRESHOLD


@cache
def _libc():
    """glibc's malloc entry points, or None where the C library is not glibc."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        functions = libc.mallopt, libc.malloc, libc.free
    except (OSError, AttributeError, TypeError):
        return None
    mallopt, malloc, free = functions
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    malloc.argtypes, malloc.restype = (ctypes.c_size_t,), ctypes.c_void_p
    free.argtypes, free.restype = (ctypes.c_void_p,), None
    return libc


@cache
def keep_freed_memory() -> bool:
    """Raises glibc malloc's mmap and trim thresholds for this process and gives all its threads one arena (once;
    threads started before keep the arena they had); False where the C library is not glibc (nothing to change
    there) or the environment says CO3SOP_KEEP_FREED_MEMORY=0."""
    libc = _libc()
    if os.environ.get("CO3SOP_KEEP_FREED_MEMORY", "1") == "0" or libc is None:
        return False
    return all(
        libc.mallopt(option, value)
        for option, value in (
            (_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
            (_M_TRIM_THRESHOLD, TRIM_THRESHOLD),
            (_M_ARENA_MAX, 1),
        )
    )


def reserve_memory(nbytes: int) -> bool:
    """Writes `nbytes` of heap (rounded up to 16 MB blocks) and frees it, after `keep_freed_memory`: the pages stay
    with the process (the trim threshold rises by the reserve, so the heap's free top is given back only beyond the
    reserve and the usual threshold) and later allocations of any thread take them without a page fault. False
    where nothing was reserved (malloc left as it is, no reserve asked for, or the memory not there)."""
    if nbytes > MAX_RESERVE:
        raise ValueError(
            f"reserve_memory: {nbytes} bytes, above the {MAX_RESERVE} that malloc's trim threshold (an int) keeps"
        )
    if nbytes <= 0 or not keep_freed_memory():
        return False
    libc = _libc()
    if not libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD + nbytes):
        return False
    blocks = []
    try:
        for _ in range(-(-nbytes // _RESERVE_BLOCK)):
            block = libc.malloc(_RESERVE_BLOCK)
            if not block:
                return False
            blocks.append(block)
            ctypes.memset(block, 0, _RESERVE_BLOCK)
    finally:
        for block in reversed(blocks):
            libc.free(block)
    return True


def freeze_setup() -> None:
    """Moves every object alive now (modules, a loaded model, compiled kernels) out of the garbage collector's
    generations, after a collection: later collections walk only what frames allocate."""
    gc.collect()
    gc.freeze()
