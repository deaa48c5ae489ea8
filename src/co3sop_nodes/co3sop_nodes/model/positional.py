"""3D sine positional encoding of voxel positions (DETR's 2D encoding extended to x, y, z)."""

from __future__ import annotations

import math

import torch


def sine_encoding_3d(positions: torch.Tensor, dims: int, temperature: float = 10000.0) -> torch.Tensor:
    """positions (Q, 3) in [0, 1] -> (Q, dims): sin/cos of each axis at geometric frequencies."""
    per_axis = 2 * math.ceil(dims / 6)  # sin + cos pairs per axis
    freq = temperature ** (2 * (torch.arange(per_axis // 2, dtype=torch.float32) / per_axis))
    angles = positions[:, :, None] * 2 * math.pi / freq  # (Q, 3, per_axis / 2)
    enc = torch.cat([angles.sin(), angles.cos()], dim=-1).reshape(len(positions), -1)  # (Q, 3 * per_axis)
    return enc[:, :dims]
