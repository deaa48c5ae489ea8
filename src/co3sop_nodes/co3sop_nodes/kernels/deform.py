"""Deformable sampling on the CPU as compiled kernels (kernels/deform_sample.c), for inference.

Image to voxel (`ImageCrossAttention`) and voxel to voxel (`DeformableAttention3d`):
the same sums as their PyTorch paths (`deform_attn.sample_2d` / `sample_3d`
with `grid_sample`, the definitions), without the (queries x heads x levels
or agents x points) intermediates those paths gather, add, sample and weight:
locations are computed per sample, values read channels-last, a head's
channels at a pixel or voxel as contiguous vectors. Threads split the queries
(ctypes releases the GIL).
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
    "deform_sample_2d": [_P, _P, _I, _I, _I, _P, _P, _P, _P, _P, _P, _I, _I],
    "deform_sample_3d": [_P, _P, _I, _I, _I, _P, _P, _P, _P, _P, _I, _I],
}


@cache
def _kernel(channels_per_head: int, name: str = "deform_sample_2d"):
    if channels_per_head % 4:
        return None  # the kernels read a head's channels as 8-lane (or 4-lane) vectors
    lib = kernels.load("deform_sample", CH=channels_per_head)
    if lib is None:
        return None
    fn = getattr(lib, name)
    fn.argtypes, fn.restype = _ARGS[name], None
    return fn


def available(channels_per_head: int) -> bool:
    """Whether the kernels exist for this head width, are enabled and compile here (compiling them on first call)."""
    return kernels.ENABLED and _kernel(channels_per_head) is not None


def sample_pairs(
    values: list[torch.Tensor],
    camera: torch.Tensor,
    query: torch.Tensor,
    uv: torch.Tensor,
    offsets: torch.Tensor,
    weights: torch.Tensor,
    threads: int,
) -> torch.Tensor:
    """values: L x (N, Hl, Wl, H*Ch) channels-last, per camera; per pair (camera, query index, uv (pairs, 2) in [0, 1]);
    offsets (Q, H, L, P, 2) in pixels of each level, weights (Q, H, L, P) -> (pairs, H*Ch). `available` first."""
    _, h, levels, p, _ = offsets.shape
    n, c = values[0].shape[0], values[0].shape[-1]
    fn = _kernel(c // h)
    maps = [kernels.array(v) for v in values]
    pointers = (ctypes.c_void_p * (n * levels))(
        *[m.ctypes.data + k * m.strides[0] for k in range(n) for m in maps]
    )  # camera-major
    shapes = np.array([m.shape[1:3] for m in maps], np.int64)  # (L, 2) Hl, Wl
    cams, queries, uvs = kernels.array(camera, np.int64), kernels.array(query, np.int64), kernels.array(uv)
    off, w = kernels.array(offsets), kernels.array(weights)
    pairs = len(cams)
    out = np.empty((pairs, c), np.float32)
    kernels.parallel(
        fn,
        (
            ctypes.addressof(pointers),
            shapes.ctypes.data,
            levels,
            h,
            p,
            cams.ctypes.data,
            queries.ctypes.data,
            uvs.ctypes.data,
            off.ctypes.data,
            w.ctypes.data,
            out.ctypes.data,
        ),
        pairs,
        threads,
    )
    return torch.from_numpy(out)


# the 3D sampler's softmax terms per query and head (agents x points) at most: MAX_TERMS in deform_sample.c
MAX_TERMS = 256


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
    with none reads nothing) -> (Q, H*Ch). `available` first."""
    a, c = values.shape[0], values.shape[-1]
    q, h, _, p, _ = offsets.shape
    if a * p > MAX_TERMS:
        raise ValueError(f"sample_3d: {a} agents x {p} points is above the kernel's {MAX_TERMS} terms")
    fn = _kernel(c // h, "deform_sample_3d")
    maps = kernels.array(values)
    pointers = (ctypes.c_void_p * a)(*[maps.ctypes.data + k * maps.strides[0] for k in range(a)])
    dims = np.array(maps.shape[1:4], np.int64)
    ref, off, w = (kernels.array(t) for t in (reference, offsets, logits))
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
            off.ctypes.data,
            w.ctypes.data,
            may.ctypes.data,
            out.ctypes.data,
        ),
        q,
        threads,
    )
    return torch.from_numpy(out)
