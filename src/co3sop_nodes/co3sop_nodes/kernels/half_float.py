"""float32 <-> float16 for the feature codec, compiled (kernels/half_float.c), as they are or byte-shuffled.

NumPy converts float16 one element at a time in software: a millisecond or more per feature volume, on every
vehicle's encoding and every decoding at the ego. The compiled loops use the CPU's conversion instructions and
give the same bits (tested); without a compiler, or a compiler without _Float16, NumPy converts. Byte-shuffled
("planes": every value's low byte, then every high byte, as the codec's shuffle-zstd sends them) in the same pass.
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np

from co3sop_nodes import kernels

_ARGS = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64]
_PLANES_ARGS = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64]


@cache
def _kernels():
    lib = kernels.load("half_float")
    if lib is None:
        return None
    for fn in (lib.to_half, lib.from_half):
        fn.argtypes, fn.restype = _ARGS, None
    for fn in (lib.to_half_planes, lib.from_half_planes):
        fn.argtypes, fn.restype = _PLANES_ARGS, None
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


def to_float16_planes(values: np.ndarray) -> np.ndarray:
    """values as float16 (as `to_float16`), byte-shuffled: (2 n,) uint8, every value's low byte, then every value's
    high byte."""
    values = np.ascontiguousarray(values, np.float32).reshape(-1)
    if not available():
        return np.ascontiguousarray(to_float16(values).view(np.uint8).reshape(-1, 2).T).reshape(-1)
    out = np.empty(2 * values.size, np.uint8)
    _kernels().to_half_planes(values.ctypes.data, out.ctypes.data, values.size, 0, values.size)
    return out


def from_float16_planes(planes: np.ndarray) -> np.ndarray:
    """`to_float16_planes`' inverse: (2 n,) uint8 -> (n,) float32, exactly."""
    planes = np.ascontiguousarray(planes, np.uint8).reshape(-1)
    if planes.size % 2:
        raise ValueError(f"from_float16_planes: {planes.size} bytes, not two planes of one byte per value")
    n = planes.size // 2
    if not available():
        return from_float16(np.ascontiguousarray(planes.reshape(2, n).T).view(np.float16).reshape(-1))
    out = np.empty(n, np.float32)
    _kernels().from_half_planes(planes.ctypes.data, out.ctypes.data, n, 0, n)
    return out
