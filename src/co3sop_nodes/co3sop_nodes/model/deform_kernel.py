"""Image-to-voxel deformable sampling on the CPU as a compiled kernel (native/deform_sample.c), for inference.

The same sums as `ImageCrossAttention`'s PyTorch path (`deform_attn.sample_2d`
with `grid_sample`, its definition), for every visible (camera, query) pair at
once, without the (pairs x heads x levels x points) intermediates that path
gathers, adds, samples and weights: locations are computed per sample, values
read channels-last, a head's channels at a pixel as contiguous vectors.
Threads split the pairs (ctypes releases the GIL).
"""

from __future__ import annotations

import ctypes
from concurrent.futures import ThreadPoolExecutor
from functools import cache

import numpy as np
import torch

from .. import native

_P = ctypes.c_void_p
_I = ctypes.c_int64


@cache
def _kernel(channels_per_head: int):
    if channels_per_head % 8:
        return None  # the kernel reads a head's channels as 8-lane vectors
    lib = native.load("deform_sample", CH=channels_per_head)
    if lib is None:
        return None
    fn = lib.deform_sample_2d
    fn.argtypes, fn.restype = [_P, _P, _I, _I, _I, _P, _P, _P, _P, _P, _P, _I, _I], None
    return fn


@cache
def _pool(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix="deform")


def available(channels_per_head: int) -> bool:
    """Whether the kernel exists for this head width and compiles here (compiling it on first call)."""
    return _kernel(channels_per_head) is not None


def _array(t: torch.Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype)


def sample_pairs(values: list[torch.Tensor], camera: torch.Tensor, query: torch.Tensor, uv: torch.Tensor, offsets: torch.Tensor,
                 weights: torch.Tensor, threads: int) -> torch.Tensor:
    """values: L x (N, Hl, Wl, H*Ch) channels-last, per camera; per pair (camera, query index, uv (pairs, 2) in [0, 1]);
    offsets (Q, H, L, P, 2) in pixels of each level, weights (Q, H, L, P) -> (pairs, H*Ch). `available` first."""
    _, h, levels, p, _ = offsets.shape
    n, c = values[0].shape[0], values[0].shape[-1]
    fn = _kernel(c // h)
    maps = [_array(v, np.float32) for v in values]
    pointers = (ctypes.c_void_p * (n * levels))(*[m.ctypes.data + k * m.strides[0] for k in range(n) for m in maps])  # camera-major
    shapes = np.array([m.shape[1:3] for m in maps], np.int64)  # (L, 2) Hl, Wl
    cams, queries, uvs = _array(camera, np.int64), _array(query, np.int64), _array(uv, np.float32)
    off, w = _array(offsets, np.float32), _array(weights, np.float32)
    pairs = len(cams)
    out = np.empty((pairs, c), np.float32)
    args = (ctypes.addressof(pointers), shapes.ctypes.data, levels, h, p, cams.ctypes.data, queries.ctypes.data, uvs.ctypes.data,
            off.ctypes.data, w.ctypes.data, out.ctypes.data)
    if threads <= 1 or pairs < 1024:
        fn(*args, 0, pairs)
    else:  # the arrays above stay referenced until every part is done
        bounds = np.linspace(0, pairs, threads + 1).astype(np.int64)
        list(_pool(threads).map(lambda i: fn(*args, int(bounds[i]), int(bounds[i + 1])), range(threads)))
    return torch.from_numpy(out)
