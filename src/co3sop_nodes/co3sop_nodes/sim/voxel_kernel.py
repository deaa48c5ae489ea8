"""The voxel sensor's stages as a compiled kernel (kernels/voxel_sensor.c): the same three stages as
voxel_sensor.py's NumPy path, per object in C, objects spread over threads.

The kernel decides overlap with the primitives' own constants (`overlap_constants`
in shapes.py) and the same float64 operations, so its grid equals the NumPy
path's and the oracle's; tests check it on random scenes and towns.
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence
from functools import cache

import numpy as np

from co3sop_nodes import kernels
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.sim.scene import SceneObject
from co3sop_nodes.sim.shapes import EPS, Box, Cylinder, Primitive

STRIDE = 96  # float64 per primitive, as kernels/voxel_sensor.c lays them out
_P, _I = ctypes.c_void_p, ctypes.c_int64


@cache
def _kernel():
    lib = kernels.load("voxel_sensor")
    if lib is None:
        return None
    lib.annotate_objects.argtypes, lib.annotate_objects.restype = (
        [_P, _P, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P],
        ctypes.c_int,
    )
    lib.ranks_to_labels.argtypes, lib.ranks_to_labels.restype = [_P, _P, _I, _I], None
    return lib


def available() -> bool:
    """Whether the kernel is enabled and compiles here (compiling it on first call)."""
    return kernels.ENABLED and _kernel() is not None


def _packed(p: Primitive) -> tuple[int, np.ndarray]:
    """(kind, params (STRIDE,)) of a primitive, as the kernel reads them."""
    out = np.zeros(STRIDE)
    if isinstance(p, Box):
        axes, abs_sum, reach = p.overlap_constants
        out[0:3], out[3:48], out[48:63], out[63:78], out[78:81], out[81:90] = (
            p.center,
            axes.ravel(),
            abs_sum,
            reach,
            p.half,
            p.rot.ravel(),
        )
        return 0, out
    if isinstance(p, Cylinder):
        out[:7] = (p.x, p.y, *p.overlap_constants, p.radius**2, p.z1)
        return 1, out
    out[:5] = (*p.center, p.overlap_constants, p.radius**2)
    return 2, out


def ranks(
    grid: GridSpec,
    objects: Sequence[SceneObject],
    rank: np.ndarray,
    boxes: np.ndarray,
    primitive_boxes: np.ndarray,
    threads: int,
) -> np.ndarray:
    """Stages 1 and 2 for every object, and the rank half of stage 3: (num_voxels,) uint8, per voxel the highest
    `rank` (N,) of an object on it, 0 where none is. boxes (N, 6) and primitive_boxes (P, 6): index boxes (lo, hi)
    of the objects and of their primitives, in order, bounding every voxel they may occupy."""
    fn = _kernel().annotate_objects
    kinds, params = zip(*(_packed(p) for o in objects for p in o.primitives)) if objects else ((), ())
    kind = np.array(kinds, np.int32)
    param = np.stack(params) if params else np.zeros((0, STRIDE))
    first = np.cumsum([0, *(len(o.primitives) for o in objects)]).astype(np.int64)
    boxes, primitive_boxes = np.ascontiguousarray(boxes, np.int64), np.ascontiguousarray(primitive_boxes, np.int64)
    order = np.argsort(-np.prod(np.maximum(boxes[:, 3:] - boxes[:, :3], 0), axis=1), kind="stable").astype(
        np.int64
    )  # largest first
    rank = np.ascontiguousarray(rank, np.uint8)
    g = np.array([*grid.origin, grid.voxel_size, EPS])
    dims = np.array(grid.dims, np.int64)
    out = np.zeros(grid.num_voxels, np.uint8)
    queue = np.zeros(1, np.int64)  # the next object to take
    args = (
        [a.ctypes.data for a in (g, dims)]
        + [len(objects)]
        + [a.ctypes.data for a in (order, first, boxes, rank, kind, param, primitive_boxes, out, queue)]
    )
    if any(kernels.together(lambda: fn(*args), threads)):
        raise MemoryError(
            f"voxel sensor: out of memory annotating {len(objects)} objects on {'x'.join(map(str, grid.dims))}"
        )
    return out


def to_labels(grid_ranks: np.ndarray, label_of_rank: np.ndarray, threads: int) -> np.ndarray:
    """Ranks to labels in place: label_of_rank (256,) uint8."""
    lut = np.ascontiguousarray(label_of_rank, np.uint8)
    kernels.parallel(_kernel().ranks_to_labels, (grid_ranks.ctypes.data, lut.ctypes.data), grid_ranks.size, threads)
    return grid_ranks
