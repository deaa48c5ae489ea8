"""A LiDAR vehicle half's output layers on an int8 path, compiled (kernels/lidar_output.c).

After the encoder's int8 layers the PyTorch path dequantizes their last uint8 volume into the path's floats (a copy
and two passes), convolves it by the 1x1 feature layer, then the features by the 1x1 confidence layer and takes its
sigmoid, and widens both into the channels-first float32 the wire's codecs take (two more copies; in float32, the
1x1 layers copy a channels-last volume first). The kernel computes each voxel's features and confidence from its
uint8 channels at once and writes them channels-first in float32: where the floats are bfloat16 rounding where that
path rounds, bit for bit; where they are float32, within float32 rounding of it.
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np
import torch
from torch import nn

from co3sop_nodes import kernels

_P, _I, _F = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
MAX_HEIGHT = 96  # the kernel's BLOCK: a column's values of one channel it holds
_ARGS = [_P, _I, _I, _I, _F, _P, _P, _P, _P, _F, _P, _P, _P, _I, _I]


@cache
def _kernel(channels: int, floats: str):
    # float32: the dequantization's product and offset rounded apart, as PyTorch's two passes round them
    bf16 = floats == "bfloat16"
    lib = kernels.load("lidar_output", contract=bf16, C=channels, BF16=int(bf16))
    if lib is None:
        return None
    fn = lib.lidar_output
    fn.argtypes, fn.restype = _ARGS, None
    return fn


FLOATS = ("bfloat16", "float32")  # the int8 path's float precisions it computes


def available(channels: int, floats: str = "bfloat16") -> bool:
    """Whether the kernel for `channels` (a multiple of 32) and an int8 path whose floats are `floats` runs here: an
    AVX-512 CPU, one that computes bfloat16 products (AVX-512 BF16) for bfloat16, and the kernel compiling (on first
    call; CO3SOP_NATIVE=0: never)."""
    flags = kernels.cpu_flags()
    return (
        channels % 32 == 0
        and floats in FLOATS
        and "avx512f" in flags
        and (floats != "bfloat16" or "avx512_bf16" in flags)
        and kernels.ENABLED
        and _kernel(channels, floats) is not None
    )


@cache
def _sigmoid() -> np.ndarray:
    """PyTorch's bfloat16 sigmoid of every bfloat16 value, by its bits (65536 uint16): the kernel looks its
    confidence up, so it is the PyTorch layer's to the bit, NaN included."""
    every = torch.arange(-(1 << 15), 1 << 15, dtype=torch.int32).to(torch.int16).view(torch.bfloat16)
    table = torch.empty(1 << 16, dtype=torch.int16)
    table[every.view(torch.int16).to(torch.int32) & 0xFFFF] = torch.sigmoid(every).view(torch.int16)
    return table.numpy().view(np.uint16)


def _bf16(t: torch.Tensor) -> np.ndarray:
    """t rounded to bfloat16 (as autocast casts a layer's weights), as float32."""
    return kernels.array(t.detach().to(torch.bfloat16).float())


def lidar_output(
    values: torch.Tensor,
    scale: float,
    offset: torch.Tensor | None,
    out: nn.Conv3d,
    confidence: nn.Conv3d,
    threads: int,
    floats: str = "bfloat16",
) -> tuple[torch.Tensor, torch.Tensor]:
    """values (1, C, Z, X, Y) uint8, channels-last in memory (the int8 layers' last volume, a z-outer view), each
    `scale` times its integer, plus `offset` (C, Z) where given -> features (1, C, X, Y, Z) and confidence
    (1, 1, X, Y, Z), contiguous float32: `out` (1x1, C -> C) of the dequantized volume and sigmoid(`confidence`
    (1x1, C -> 1)) of that, as an int8 path whose floats are `floats` computes them (bfloat16: bit for bit;
    float32: within float32 rounding; both tested against it); the kernel must be `available`."""
    b, c, nz, nx, ny = values.shape
    if b != 1 or values.dtype != torch.uint8 or not values.is_contiguous(memory_format=torch.channels_last_3d):
        raise ValueError(f"lidar_output: one channels-last uint8 volume, not {values.dtype} {tuple(values.shape)}")
    if nz > MAX_HEIGHT:
        raise ValueError(f"lidar_output: volumes {MAX_HEIGHT} voxels high at most, not {nz}")
    as_floats = _bf16 if floats == "bfloat16" else kernels.array  # weights as the path's layers take them
    weight, bias = as_floats(out.weight.view(c, c)), as_floats(out.bias)  # (C out, C in), (C,)
    conf_w, conf_b = as_floats(confidence.weight.view(c)), float(as_floats(confidence.bias)[0])
    steps = None if offset is None else as_floats(offset.t())  # (Z, C)
    features = torch.empty((1, c, nx, ny, nz), dtype=torch.float32)
    conf = torch.empty((1, 1, nx, ny, nz), dtype=torch.float32)
    args = (
        values.data_ptr(),
        nz,
        nx,
        ny,
        scale,
        None if steps is None else steps.ctypes.data,
        weight.ctypes.data,
        bias.ctypes.data,
        conf_w.ctypes.data,
        conf_b,
        _sigmoid().ctypes.data if floats == "bfloat16" else None,
        features.data_ptr(),
        conf.data_ptr(),
    )
    kernels.parallel(_kernel(c, floats), args, nx * ny, threads, 64)
    return features, conf
