"""Deformable sampling on the CPU as compiled kernels (kernels/deform_sample.c), for inference.

Image to voxel (`ImageCrossAttention`) and voxel to voxel (`DeformableAttention3d`):
the same sums as their PyTorch paths (the attention weights' softmax, then
`deform_attn.sample_2d` / `sample_3d` with `grid_sample`, the definitions, and
for images the mean over the cameras that see a query), without the (queries x
heads x levels or agents x points) intermediates those paths gather, add,
sample and weight: locations and weights are computed per sample, values read
channels-last, a head's channels at a pixel or voxel as contiguous vectors.
Threads split the queries (ctypes releases the GIL).
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np
import torch

from co3sop_nodes import kernels

_P = ctypes.c_void_p
_I = ctypes.c_int64


_ARGS = {
    "deform_sample_2d": [_P, _P, _I, _I, _I, _I, _I, _P, _P, _P, _P, _P, _I, _I],
    "deform_sample_3d": [_P, _P, _I, _I, _I, _P, _P, _P, _P, _P, _I, _I],
}
# the attention's softmax terms per query and head (levels x points, agents x points) at most: MAX_TERMS in
# deform_sample.c
MAX_TERMS = 256


@cache
def _kernel(channels_per_head: int, name: str = "deform_sample_2d"):
    if channels_per_head % 4:
        return None  # the kernels read a head's channels as 8-lane (or 4-lane) vectors
    lib = kernels.load("deform_sample", CH=channels_per_head)
    if lib is None:
        return None
    fn = getattr(lib, name)
    fn.argtypes, fn.restype = _ARGS[name.removesuffix("_bf16")], None
    return fn


def available(channels_per_head: int, terms: int = 1) -> bool:
    """Whether the kernels exist for this head width and `terms` softmax terms per query and head (at most
    MAX_TERMS), are enabled and compile here (compiling them on first call)."""
    return kernels.ENABLED and terms <= MAX_TERMS and _kernel(channels_per_head) is not None


def _as_read(*tensors: torch.Tensor) -> tuple[str, list[torch.Tensor]]:
    """The kernel's name suffix and `tensors` as it reads them: as a reduced path's products wrote them where all
    are bfloat16 (widening them here would cost more than sampling), else float32; contiguous, on the CPU (the
    caller keeps them referenced while the kernel runs)."""
    if all(t.dtype == torch.bfloat16 for t in tensors):
        return "_bf16", [t.detach().cpu().contiguous() for t in tensors]
    return "", [t.detach().cpu().float().contiguous() for t in tensors]


def _terms(name: str, terms: int) -> None:
    if terms > MAX_TERMS:
        raise ValueError(f"{name}: {terms} softmax terms per query and head, above the kernel's {MAX_TERMS}")


def sample_cameras(
    values: list[torch.Tensor],
    uv: torch.Tensor,
    visible: torch.Tensor,
    offsets: torch.Tensor,
    logits: torch.Tensor,
    threads: int,
) -> torch.Tensor:
    """values: L x (N, Hl, Wl, H*Ch) channels-last, per camera; uv (N, Q, 2) in [0, 1], each query's projection in
    each camera; visible (N, Q) bool; offsets (Q, H, L, P, 2) in pixels of each level; logits (Q, H, L*P) of the
    attention weights (softmax over a query's levels and points per head) -> (Q, H*Ch): the mean over the cameras
    that see a query of its samples in each (zeros where none does). `available` first."""
    q, h, levels, p, _ = offsets.shape
    n, c = values[0].shape[0], values[0].shape[-1]
    _terms("sample_cameras", levels * p)
    suffix, (off, w) = _as_read(offsets, logits)
    fn = _kernel(c // h, "deform_sample_2d" + suffix)
    maps = [kernels.array(v) for v in values]
    if max(m[0].size for m in maps) >= 2**31:
        raise ValueError("sample_cameras: a feature map of 2^31 elements or more, beyond the kernel's int32 indices")
    pointers = (ctypes.c_void_p * (n * levels))(
        *[m.ctypes.data + k * m.strides[0] for k in range(n) for m in maps]
    )  # camera-major
    shapes = np.array([m.shape[1:3] for m in maps], np.int64)  # (L, 2) Hl, Wl
    uvs, seen = kernels.array(uv), kernels.array(visible, np.uint8)
    out = np.empty((q, c), np.float32)
    kernels.parallel(
        fn,
        (
            ctypes.addressof(pointers),
            shapes.ctypes.data,
            n,
            levels,
            h,
            p,
            q,
            uvs.ctypes.data,
            seen.ctypes.data,
            off.data_ptr(),
            w.data_ptr(),
            out.ctypes.data,
        ),
        q,
        threads,
    )
    return torch.from_numpy(out)


def sample_3d(
    values: torch.Tensor,
    reference: torch.Tensor,
    offsets: torch.Tensor,
    logits: torch.Tensor,
    allowed: torch.Tensor,
    threads: int,
) -> torch.Tensor:
    """values (A, X, Y, Z, H*Ch) channels-last; reference (Q, 3) in [0, 1]; offsets (Q, H, A, P, 3) in voxels; logits
    (Q, H, A, P) of the attention weights, softmax over the agents `allowed` (Q, A) bool and their points (a query
    with none reads nothing) -> (Q, H*Ch). Values, offsets and logits all bfloat16 (a reduced path's projections)
    are read as they are, else each as float32. `available` first."""
    a, c = values.shape[0], values.shape[-1]
    q, h, _, p, _ = offsets.shape
    _terms("sample_3d", a * p)
    suffix, (maps, off, w) = _as_read(values, offsets, logits)
    fn = _kernel(c // h, "deform_sample_3d" + suffix)
    if maps[0].numel() >= 2**31:
        raise ValueError("sample_3d: a volume of 2^31 elements or more, beyond the kernel's int32 indices")
    volume = maps.stride(0) * maps.element_size()
    pointers = (ctypes.c_void_p * a)(*[maps.data_ptr() + k * volume for k in range(a)])
    dims = np.array(maps.shape[1:4], np.int64)
    ref = kernels.array(reference)
    may = kernels.array(allowed, np.uint8)
    out = np.empty((q, c), np.float32)
    kernels.parallel(
        fn,
        (
            ctypes.addressof(pointers),
            dims.ctypes.data,
            a,
            h,
            p,
            ref.ctypes.data,
            off.data_ptr(),
            w.data_ptr(),
            may.ctypes.data,
            out.ctypes.data,
        ),
        q,
        threads,
    )
    return torch.from_numpy(out)
