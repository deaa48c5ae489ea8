"""A LiDAR vehicle half's first layer on a reduced-precision path, compiled (kernels/occupancy_conv.c).

The layer convolves the voxelised scan, one binary channel of which about 1 % is occupied, with stride 2: oneDNN
reads every voxel of it (in bfloat16, after two conversions of the whole grid) and writes its output in a layout
the next layer converts. The kernel adds each occupied voxel's taps to the outputs it reaches, applies the ReLU and
writes in the layout the next layer takes (channels-last or z-outer) in the path's precision: float32, bfloat16, or
uint8 quantized for an int8 layer after it. Its sums are float32 in another order than the convolution's, so it
serves reduced-precision paths only, within their tolerance (tested against the float32 layer).
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np
import torch

from co3sop_nodes import kernels

_ARGS = [ctypes.c_void_p, *[ctypes.c_int64] * 3, *[ctypes.c_void_p] * 3, *[ctypes.c_int64] * 5, ctypes.c_float]
# what the kernel writes -> its OUT define
OUTPUTS = {torch.float32: 0, torch.bfloat16: 1, torch.uint8: 2}


@cache
def _kernel(channels: int, dtype: torch.dtype):
    lib = kernels.load("occupancy_conv", C=channels, OUT=OUTPUTS[dtype])
    if lib is None:
        return None
    fn = lib.occupancy_conv
    fn.argtypes, fn.restype = _ARGS, ctypes.c_int
    return fn


def available(channels: int, dtype: torch.dtype) -> bool:
    """Whether the kernel for `channels` writing `dtype` (float32, bfloat16 or uint8) compiles here (compiling it
    on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernel(channels, dtype) is not None


def occupancy_conv_relu(
    occupancy: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor,
    dtype: torch.dtype,
    threads: int,
    z_outer: bool = False,
    scale: float = 1.0,
) -> torch.Tensor:
    """relu(conv3d(occupancy, weight, bias, stride=2, padding=1)) for a binary occupancy (B, 1, X, Y, Z) (uint8 or
    bool, on the CPU) and weight (C, 1, 3, 3, 3) -> (B, C, ceil(X/2), ceil(Y/2), ceil(Z/2)), channels-last in memory
    (with `z_outer`, z-outer: conv_norm.z_outer's layout), in `dtype`: float32, bfloat16, or uint8 (quantized with
    `scale`, zero point 0); the kernel must be `available`."""
    b, _, nx, ny, nz = occupancy.shape
    c = weight.shape[0]
    fn = _kernel(c, dtype)
    taps = kernels.array(weight[:, 0].permute(1, 2, 3, 0))  # (3, 3, 3, C)
    shift = kernels.array(bias)  # (C,)
    x2, y2, z2 = (nx + 1) // 2, (ny + 1) // 2, (nz + 1) // 2
    if z_outer:
        out = torch.empty((b, z2, x2, y2, c), dtype=dtype).permute(0, 2, 3, 1, 4)  # (B, X2, Y2, Z2, C) view
    else:
        out = torch.empty((b, x2, y2, z2, c), dtype=dtype)
    for i in range(b):
        grid = np.ascontiguousarray(occupancy[i, 0].cpu().numpy()).view(np.uint8)  # (X, Y, Z)
        pointers = (grid.ctypes.data, nx, ny, nz, taps.ctypes.data, shift.ctypes.data, out[i].data_ptr())
        pointers += tuple(out[i].stride()[:3])  # x, y, z strides in elements
        failed = []  # a part's nonzero return: its scratch slab could not be allocated
        # an item is a whole output x-slab: two are worth a thread
        kernels.parallel(lambda *part: failed.append(fn(*pointers, *part, scale)), (), out.shape[1], threads, 2)
        if any(failed):
            raise MemoryError("occupancy_conv: no memory for its scratch slab")
    return out.permute(0, 4, 1, 2, 3)  # (B, C, X2, Y2, Z2)
