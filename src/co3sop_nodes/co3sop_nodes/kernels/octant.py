"""The head's full-resolution stage on the CPU as a compiled kernel (kernels/octant_labels.c).

Parent features at 1/2 -> labels and confidence of their 8 octants, two
parents at a time with their octants in one 16-lane vector: the transposed
convolution, the pointwise layer, the classifier, the argmax and the label's
softmax probability, never materialising the (N, 8, C) and (N, 8, K)
intermediates that `OccupancyHead.labels`' PyTorch loop spends its time
writing and reading. Threads split the parents (ctypes releases the GIL).
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np
import torch

from co3sop_nodes import kernels

_POINTER = ctypes.c_void_p
_ARGS = [_POINTER, *[ctypes.c_int64] * 7, *[_POINTER] * 8]


def dot_bf16(precision: str, c2: int) -> bool:
    """Whether the kernel for `precision` takes its products as bfloat16 dot products of channel pairs: bfloat16 or
    int8 inference on a CPU that computes them (AVX-512 BF16, which every CPU with AMX also has), C2 even."""
    return precision in ("bfloat16", "int8") and c2 % 2 == 0 and "avx512_bf16" in kernels.cpu_flags()


@cache
def _kernel(c1: int, c2: int, classes: int, precision: str):
    reduced = precision != "float32"
    lib = kernels.load(
        "octant_labels",
        contract=reduced,
        C1=c1,
        C2=c2,
        K=classes,
        REDUCED=int(reduced),
        PARENTS_BF16=int(precision == "bfloat16"),
        PARENTS_U8=int(precision == "int8"),
        DOT_BF16=int(dot_bf16(precision, c2)),
    )
    if lib is None:
        return None
    fn = lib.octant_labels
    fn.argtypes, fn.restype = _ARGS, None
    return fn


def available(c1: int, c2: int, classes: int, precision: str = "float32") -> bool:
    """Whether the kernel for this head shape and inference precision (see `octant_labels`) compiles here (compiling
    it on first call; CO3SOP_NATIVE=0: never). It reads parents' channels in pairs: C1 must be even."""
    return c1 % 2 == 0 and kernels.ENABLED and _kernel(c1, c2, classes, precision) is not None


def octant_labels(
    parents: torch.Tensor,
    up: torch.nn.ConvTranspose3d,
    point: torch.nn.Conv3d,
    classify: torch.nn.Conv3d,
    threads: int,
    precision: str = "float32",
    scale: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """parents (X1, Y1, Z1, C1) of the 1/2 grid on the CPU, in any memory layout with channels innermost (others are
    copied) -> labels, confidence (2X1, 2Y1, 2Z1) uint8, on `threads` threads (the kernel must be `available`) for an
    inference path of `precision`. float32: every sum rounded as the reference rounds it. A reduced precision: fused
    multiply-adds and a shorter exp (labels equal but for near-ties, confidence within one step, as tested);
    bfloat16 parents are read as they are (widening them first would be one more pass over the volume), and where
    `dot_bf16` the layers compute as bfloat16 layers do (tested against that definition). int8: uint8 parents of an
    int8 head, each value `scale` times its integer, read as they are; the rest as a reduced precision, its products
    in bfloat16 where `dot_bf16` (the integers exact, the scaled weights rounded)."""
    c1, c2, k = up.in_channels, up.out_channels, classify.out_channels
    fn = _kernel(c1, c2, k, precision)
    dtype = {"bfloat16": torch.bfloat16, "int8": torch.uint8}.get(precision, torch.float32)
    if precision == "int8" and parents.dtype != torch.uint8:
        raise ValueError(f"octant_labels: int8 takes uint8 parents, not {parents.dtype}")
    x = parents.detach().cpu().to(dtype)
    if x.stride(-1) != 1:
        x = x.contiguous()
    # (C1, C2, 16) in the kernel's lane order: octant (dx, dy, dz) of parent `half` at lane 4 (2 dx + dy) + 2 half + dz
    up_w = up.weight.flatten(2).view(c1, c2, 4, 1, 2).expand(c1, c2, 4, 2, 2).reshape(c1, c2, 16)
    up_w = kernels.array(up_w * scale if precision == "int8" else up_w)
    up_b = kernels.array(up.bias[:, None].expand(c2, 16))  # (C2, 16)
    point_w, point_b = (
        kernels.array(point.weight[:, :, 0, 0, 0].t()),
        kernels.array(point.bias),
    )  # (C2 in, C2 out), (C2,)
    cls_w, cls_b = kernels.array(classify.weight[:, :, 0, 0, 0].t()), kernels.array(classify.bias)  # (C2, K), (K,)
    x1, y1, z1 = x.shape[:3]
    labels, confidence = np.empty((2 * x1, 2 * y1, 2 * z1), np.uint8), np.empty((2 * x1, 2 * y1, 2 * z1), np.uint8)
    ptrs = [a.ctypes.data for a in (up_w, up_b, point_w, point_b, cls_w, cls_b, labels, confidence)]
    grid = (x.data_ptr(), *x.stride()[:3], y1, z1)  # the parents and their strides in elements
    kernels.parallel(lambda *bounds: fn(*grid, *bounds, *ptrs), (), x1 * y1 * z1, threads)
    return torch.from_numpy(labels), torch.from_numpy(confidence)
