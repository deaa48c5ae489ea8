"""3D sine positional encoding of voxel positions (DETR's 2D encoding extended to x, y, z)."""

from __future__ import annotations

import math

import torch


def sine_encoding_3d(positions: torch.Tensor, dims: int, temperature: float = 10000.0) -> torch.Tensor:
    """positions (Q, 3) in [0, 1] -> (Q, dims): sin/cos of each axis at geometric frequencies.

    Every axis gets the same number of sin/cos pairs (at least one); leftover
    dimensions are zero, so no axis is ever cut off.
    """
    pairs = max(1, dims // 6)
    freq = temperature ** (torch.arange(pairs, dtype=torch.float32) / pairs)
    angles = positions[:, :, None] * 2 * math.pi / freq  # (Q, 3, pairs)
    enc = torch.cat([angles.sin(), angles.cos()], dim=-1).reshape(len(positions), -1)  # (Q, 6 * pairs)
    return torch.nn.functional.pad(enc, (0, max(0, dims - enc.shape[1])))[:, :dims]
