"""The voxels of a label grid a viewer can see, as coloured points, compiled (kernels/visible_voxels.c).

Every ego draws its prediction and the recorder the ego's ground truth, once a frame each: NumPy's version of it
(viz/cloud.py, the definition) passes over the 1.6 million voxels of the 51.2 m grid a dozen times and fills the
points field by field. The kernel reads the grid once, marking a plane at a time in a scratch that stays in cache, and
writes each point's 20 bytes at once, the same bytes (tested).
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np

from co3sop_nodes import kernels
from co3sop_nodes.common.classes import EMPTY, IGNORE

_POINTER = ctypes.c_void_p


@cache
def _kernels():
    lib = kernels.load("visible_voxels", EMPTY=EMPTY, IGNORE=IGNORE)
    if lib is None:
        return None
    points = lib.visible_points
    points.argtypes = [_POINTER, *[ctypes.c_int64] * 3, *[_POINTER] * 6]
    points.restype = ctypes.c_int64
    return lib


def available() -> bool:
    """Whether the kernel compiles here (compiling it on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernels() is not None


def visible_points(labels: np.ndarray, centres: list[np.ndarray], colours: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """labels (X, Y, Z) uint8, centres per axis (X,), (Y,), (Z,) float64, colours (256,) uint32 per label value ->
    (N,) points of `dtype` (LABEL_POINTS' layout: x, y, z float32, the colour, the label, zero padding), one per
    visible voxel in C order; the kernel must be `available`."""
    if dtype.itemsize != 20:
        raise ValueError(f"visible_points writes 20-byte points, not {dtype.itemsize}")
    lib = _kernels()
    labels = np.ascontiguousarray(labels, np.uint8)
    nx, ny, nz = labels.shape
    scratch = np.zeros((5, ny + 2, nz + 2), np.uint8)  # three planes' shown flags, a plane's marks, its flags
    # room for every voxel: only the pages written are ever touched, a grid's points a fraction of it
    points = np.empty(labels.size, dtype)
    cx, cy, cz = (np.ascontiguousarray(c, np.float64) for c in centres)
    rgb = np.ascontiguousarray(colours, np.uint32)
    count = lib.visible_points(
        labels.ctypes.data, nx, ny, nz, scratch.ctypes.data, cx.ctypes.data, cy.ctypes.data, cz.ctypes.data,
        rgb.ctypes.data, points.ctypes.data,
    )  # fmt: skip
    return points[:count]
