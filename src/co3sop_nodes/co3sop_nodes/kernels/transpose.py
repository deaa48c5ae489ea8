"""A float32 matrix transposed into a new contiguous one, compiled (kernels/transpose.c): volumes moved between
channels-first (C, V) and channels-last (V, C) layouts, several times faster than PyTorch's copy of a transposed
view; a bfloat16 one widened to float32 on the way (a reduced path's output handed on in float32). Bit for bit a
copy (tested)."""

from __future__ import annotations

import ctypes
from functools import cache

import torch

from co3sop_nodes import kernels

# the element types the kernel reads -> its function (it writes float32)
_FUNCTIONS = {torch.float32: "transpose", torch.bfloat16: "transpose_bf16"}


@cache
def _kernel(dtype: torch.dtype = torch.float32):
    lib = kernels.load("transpose")
    if lib is None:
        return None
    fn = getattr(lib, _FUNCTIONS[dtype])
    fn.argtypes, fn.restype = [ctypes.c_void_p, ctypes.c_void_p, *[ctypes.c_int64] * 4], None
    return fn


def available() -> bool:
    """Whether the kernel compiles here (compiling it on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernel() is not None


def transposed(
    x: torch.Tensor, threads: int = 1, out: torch.Tensor | None = None, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """x (R, S) -> x.t() as a contiguous (S, R) tensor of `dtype` (default x's), written into `out` where given
    (contiguous, (S, R), of that dtype). The compiled kernel for a float32 CPU matrix, or a bfloat16 one into
    float32, whose rows are contiguous and that takes no gradient (where it compiles; CO3SOP_NATIVE=0: never),
    PyTorch's copy otherwise."""
    r, s = x.shape
    dtype = x.dtype if dtype is None else dtype
    if out is None:
        out = torch.empty(s, r, dtype=dtype, device=x.device)
    elif out.shape != (s, r) or out.dtype != dtype or not out.is_contiguous():
        raise ValueError(f"transposed: out must be a contiguous ({s}, {r}) {dtype} tensor, not {tuple(out.shape)}")
    fits = x.dtype in _FUNCTIONS and out.dtype == torch.float32 and x.device.type == "cpu" and x.stride(1) == 1
    fits = fits and not (torch.is_grad_enabled() and x.requires_grad)
    if not (fits and available()):
        return out.copy_(x.t())
    kernels.parallel(_kernel(x.dtype), (x.data_ptr(), out.data_ptr(), r, x.stride(0)), s, threads, 64)
    return out


def channels_first_float32(volume: torch.Tensor, threads: int = 1) -> torch.Tensor:
    """volume (B, C, X, Y, Z) -> a contiguous float32 copy (the volume itself where it is one): a channels-last CPU
    one that takes no gradient by `transposed`, one sample at a time, any other by PyTorch's copy."""
    b, c = volume.shape[:2]
    rows = volume.permute(0, 2, 3, 4, 1)  # (B, X, Y, Z, C): contiguous where the volume is channels-last
    copy = volume.dtype == torch.float32 and volume.is_contiguous() or not rows.is_contiguous() or c == 1
    if copy or volume.device.type != "cpu" or (torch.is_grad_enabled() and volume.requires_grad):
        out = volume.to(torch.float32, memory_format=torch.contiguous_format)  # float32 already: itself
        return out if out.is_contiguous() else out.contiguous()
    out = torch.empty(volume.shape, dtype=torch.float32, device=volume.device)
    for i in range(b):
        transposed(rows[i].reshape(-1, c), threads, out[i].view(c, -1), torch.float32)
    return out
