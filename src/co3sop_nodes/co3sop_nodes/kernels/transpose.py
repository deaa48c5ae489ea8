"""A float32 matrix transposed into a new contiguous one, compiled (kernels/transpose.c): volumes moved between
channels-first (C, V) and channels-last (V, C) layouts, several times faster than PyTorch's copy of a transposed
view. Bit for bit a copy (tested)."""

from __future__ import annotations

import ctypes
from functools import cache

import torch

from co3sop_nodes import kernels


@cache
def _kernel():
    lib = kernels.load("transpose")
    if lib is None:
        return None
    fn = lib.transpose
    fn.argtypes, fn.restype = [ctypes.c_void_p, ctypes.c_void_p, *[ctypes.c_int64] * 4], None
    return fn


def available() -> bool:
    """Whether the kernel compiles here (compiling it on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernel() is not None


def transposed(x: torch.Tensor, threads: int = 1, out: torch.Tensor | None = None) -> torch.Tensor:
    """x (R, S) -> x.t() as a contiguous (S, R) tensor, written into `out` where given (contiguous, float32, (S, R)).
    The compiled kernel for a float32 CPU matrix whose rows are contiguous and that takes no gradient (where it
    compiles; CO3SOP_NATIVE=0: never), PyTorch's copy otherwise."""
    r, s = x.shape
    if out is None:
        out = torch.empty(s, r, dtype=x.dtype, device=x.device)
    elif out.shape != (s, r) or out.dtype != x.dtype or not out.is_contiguous():
        raise ValueError(f"transposed: out must be a contiguous ({s}, {r}) {x.dtype} tensor, not {tuple(out.shape)}")
    fits = x.dtype == out.dtype == torch.float32 and x.device.type == "cpu" and x.stride(1) == 1
    fits = fits and not (torch.is_grad_enabled() and x.requires_grad)
    if not (fits and available()):
        return out.copy_(x.t())
    kernels.parallel(_kernel(), (x.data_ptr(), out.data_ptr(), r, x.stride(0)), s, threads, 64)
    return out
