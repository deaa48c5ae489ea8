"""A residual sum and its layer norm as one compiled pass (kernels/layer_norm.c), for inference.

The transformers' post-norm blocks (LayerNorm(x + f(x)), over rows of 32 or 48 channels) spend about as long in
PyTorch's add and layer norm as in the products around them: per row, not per channel. Equal to
`F.layer_norm(x + y)` within float rounding (tested); x and y float32 or bfloat16, the result float32.
"""

from __future__ import annotations

import ctypes
from functools import cache

import torch

from co3sop_nodes import kernels

_P, _I = ctypes.c_void_p, ctypes.c_int64
_READS = (torch.float32, torch.bfloat16)


@cache
def _kernel(channels: int):
    if channels % 8:
        return None  # a row is read as whole vectors of 8
    lib = kernels.load("layer_norm", C=channels)
    if lib is None:
        return None
    fn = lib.add_layer_norm
    fn.argtypes, fn.restype = [_P, _I, _P, _I, _P, _P, ctypes.c_float, _P, _I, _I], None
    return fn


def available(channels: int) -> bool:
    """Whether the kernel for rows of `channels` compiles here (compiling it on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernel(channels) is not None


def fits(x: torch.Tensor, y: torch.Tensor) -> bool:
    """Whether `add_layer_norm` takes x and y (..., C): on the CPU, of one shape, float32 or bfloat16, and the kernel
    for C `available`."""
    return (
        x.shape == y.shape
        and x.device.type == y.device.type == "cpu"
        and x.dtype in _READS
        and y.dtype in _READS
        and available(x.shape[-1])
    )


def add_layer_norm(
    x: torch.Tensor, y: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, eps: float, threads: int
) -> torch.Tensor:
    """LayerNorm(x + y) over the last axis with `weight` and `bias` (C,): x, y (..., C) -> (..., C) float32, rows
    split over `threads`. `fits` first."""
    c = x.shape[-1]
    rows = x.numel() // c
    xs, ys = x.detach().contiguous(), y.detach().contiguous()
    w, b = (t.detach().float().contiguous() for t in (weight, bias))
    out = torch.empty(x.shape, dtype=torch.float32)
    args = (
        xs.data_ptr(),
        xs.dtype == torch.bfloat16,
        ys.data_ptr(),
        ys.dtype == torch.bfloat16,
        w.data_ptr(),
        b.data_ptr(),
        eps,
        out.data_ptr(),
    )
    kernels.parallel(_kernel(c), args, rows, threads)
    return out
