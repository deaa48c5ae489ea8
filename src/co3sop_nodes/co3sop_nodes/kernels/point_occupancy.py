"""LiDAR points binned into a grid's occupancy, compiled (kernels/point_occupancy.c).

Every LiDAR vehicle bins its scan once a frame, and training bins every sample's: NumPy's version of it
(inference/inputs.py, the definition) makes half a dozen passes over the points through temporaries; the kernel
makes one, the same voxels (tested).
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np

from co3sop_nodes import kernels
from co3sop_nodes.common.grid import GridSpec


@cache
def _kernel():
    lib = kernels.load("point_occupancy")
    if lib is None:
        return None
    fn = lib.point_occupancy
    fn.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p, ctypes.c_double]
    fn.argtypes += [*[ctypes.c_int64] * 3, ctypes.c_void_p]
    fn.restype = None
    return fn


def available() -> bool:
    """Whether the kernel compiles here (compiling it on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernel() is not None


def fits(points: np.ndarray) -> bool:
    """Whether the kernel takes these points: float32 (N, >= 3) with whole rows in memory one after another."""
    return (
        points.dtype == np.float32
        and points.ndim == 2
        and points.shape[1] >= 3
        and points.strides[1] == 4
        and points.strides[0] % 4 == 0
    )


def point_occupancy(points: np.ndarray, grid: GridSpec) -> np.ndarray:
    """points (N, >= 3) float32 that `fit`, x, y, z first -> (X, Y, Z) uint8 occupancy of `grid`; the kernel must
    be `available`."""
    occupancy = np.zeros(grid.dims, np.uint8)
    origin = np.ascontiguousarray(grid.origin, np.float64)
    nx, ny, nz = grid.dims
    _kernel()(
        points.ctypes.data, len(points), points.strides[0] // 4, origin.ctypes.data, float(grid.voxel_size),
        nx, ny, nz, occupancy.ctypes.data,
    )  # fmt: skip
    return occupancy
