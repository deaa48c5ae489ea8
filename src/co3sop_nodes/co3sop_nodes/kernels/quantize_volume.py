"""A float32 volume quantized to uint8 in one compiled pass (kernels/quantize_volume.c), for the int8 head's input.

PyTorch takes six passes (scale, shift, round, clamp, convert, and the copy into oneDNN's z-outer layout); the
kernel reads the channels-last volume once and writes the z-outer uint8 one, bit for bit theirs (tested).
"""

from __future__ import annotations

import ctypes
from functools import cache

import torch

from co3sop_nodes import kernels


@cache
def _kernel(channels: int):
    lib = kernels.load("quantize_volume", C=channels)
    if lib is None:
        return None
    fn = lib.quantize_z_outer
    fn.argtypes = [ctypes.c_void_p, ctypes.c_float, ctypes.c_float, ctypes.c_void_p, *[ctypes.c_int64] * 4]
    fn.restype = None
    return fn


def available(channels: int) -> bool:
    """Whether the kernel for `channels` compiles here (compiling it on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernel(channels) is not None


def fits(x: torch.Tensor) -> bool:
    """Whether `quantized_z_outer` takes x (B, C, X, Y, Z): float32 on the CPU, channels-last in memory, and the
    kernel for C `available`."""
    return (
        x.dim() == 5
        and x.dtype == torch.float32
        and x.device.type == "cpu"
        and x.permute(0, 2, 3, 4, 1).is_contiguous()
        and available(x.shape[1])
    )


def quantized_z_outer(x: torch.Tensor, inverse_scale: float, zero: int, threads: int) -> torch.Tensor:
    """x (B, C, X, Y, Z) -> (B, Z, X, Y, C) uint8, contiguous: x * inverse_scale + zero (in float32) rounded to
    nearest even and clamped to [0, 255], as `(x.permute(0, 4, 2, 3, 1) * inverse_scale).add_(zero).round_()
    .clamp_(0, 255).to(torch.uint8)` computes it. `fits` first."""
    b, c, nx, ny, nz = x.shape
    out = torch.empty(b, nz, nx, ny, c, dtype=torch.uint8)
    args = (x.data_ptr(), inverse_scale, float(zero), out.data_ptr(), nx * ny, nz)
    kernels.parallel(_kernel(c), args, b * nz, threads, 2)
    return out
