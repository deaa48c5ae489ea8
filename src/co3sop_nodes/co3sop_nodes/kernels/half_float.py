"""float32 <-> float16 for the feature codec, compiled (kernels/half_float.c).

NumPy converts float16 one element at a time in software: a millisecond or more per feature volume, on every
vehicle's encoding and every decoding at the ego. The compiled loop uses the CPU's conversion instructions and
gives the same bits (tested); without a compiler, or a compiler without _Float16, NumPy converts.
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np

from co3sop_nodes import kernels

_ARGS = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64]


@cache
def _kernels():
    lib = kernels.load("half_float")
    if lib is None:
        return None
    for fn in (lib.to_half, lib.from_half):
        fn.argtypes, fn.restype = _ARGS, None
    return lib


def available() -> bool:
    """Whether the compiled conversions compile here (compiling them on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernels() is not None


def _convert(values: np.ndarray, src: type, dst: type, name: str) -> np.ndarray:
    values = np.ascontiguousarray(values, src)
    if not available():
        with np.errstate(over="ignore"):  # as the compiled loop: beyond float16's range is infinity, said by callers
            return values.astype(dst)
    out = np.empty(values.shape, dst)
    getattr(_kernels(), name)(values.ctypes.data, out.ctypes.data, 0, values.size)
    return out


def to_float16(values: np.ndarray) -> np.ndarray:
    """values as float16, rounded to nearest even (values beyond its range become infinite): `astype(np.float16)`."""
    return _convert(values, np.float32, np.float16, "to_half")


def from_float16(values: np.ndarray) -> np.ndarray:
    """float16 values as float32 (exactly): `astype(np.float32)`."""
    return _convert(values, np.float16, np.float32, "from_half")
