"""The residual sum of two uint8-quantized volumes, requantized, compiled (kernels/quantized_add.c).

oneDNN's quantized 3D convolution takes no post-operation, so an int8 residual block's sum is a pass of its own:
one over uint8 memory here, where PyTorch's float operations take four (widen, scale, add, requantize). It adds
an offset per z-layer and channel, the int8 path's correction of the empty grid's background (model/quantized.py).
"""

from __future__ import annotations

import ctypes
from functools import cache

import torch

from co3sop_nodes import kernels

_ARGS = [ctypes.c_void_p, ctypes.c_float, ctypes.c_void_p, ctypes.c_float, ctypes.c_void_p, ctypes.c_void_p]


@cache
def _kernel(channels: int):
    lib = kernels.load("quantized_add", contract=True, C=channels)
    if lib is None:
        return None
    fn = lib.quantized_add
    fn.argtypes, fn.restype = [*_ARGS, *[ctypes.c_int64] * 4], None
    return fn


def available(channels: int) -> bool:
    """Whether the kernel for `channels` compiles here (compiling it on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernel(channels) is not None


def quantized_add(
    a: torch.Tensor, a_scale: float, b: torch.Tensor, b_scale: float, scale: float, offset: torch.Tensor, threads: int
) -> torch.Tensor:
    """a a_scale + b b_scale + offset scale, quantized with `scale` (zero points 0, rounded to nearest even, clamped
    to [0, 255]), for uint8 volumes (B, C, Z, X, Y) of one shape, channels-last in memory (z-outer volumes' views),
    on the CPU, and offset (C, Z) in steps of `scale`: the result in their layout; must be `available`."""
    bsz, c, nz, nx, ny = a.shape
    layout = torch.channels_last_3d
    if a.shape != b.shape or not (a.is_contiguous(memory_format=layout) and b.is_contiguous(memory_format=layout)):
        raise ValueError(f"quantized_add: channels-last volumes of one shape, not {tuple(a.shape)}, {tuple(b.shape)}")
    if {a.dtype, b.dtype} != {torch.uint8} or offset.shape != (c, nz):
        raise ValueError(f"quantized_add: uint8 volumes and a ({c}, {nz}) offset, not {tuple(offset.shape)}")
    out = torch.empty_like(a)  # a's layout
    steps = kernels.array(offset.t())  # (Z, C)
    args = (
        a.data_ptr(),
        a_scale / scale,
        b.data_ptr(),
        b_scale / scale,
        steps.ctypes.data,
        out.data_ptr(),
        nz,
        nx * ny,
    )
    kernels.parallel(_kernel(c), args, bsz * nz, threads, 2)
    return out
