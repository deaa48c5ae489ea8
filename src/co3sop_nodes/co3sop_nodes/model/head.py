"""Prediction head: 3D convolutions and transposed convolutions to logits at 1/4, 1/2 and full resolution.

Full resolution holds 64x the voxels of 1/4, so it gets only a stride-2
transposed convolution (each fine voxel reads one coarse voxel) and pointwise
layers, without batch norm: a fine voxel's logits then depend on its parent
voxel alone, and `forward_at` evaluates them for chosen voxels only, exactly
as the dense pass would (training samples voxels there; tests check equality).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm3d(cout), nn.ReLU(inplace=True))


class OccupancyHead(nn.Module):
    def __init__(self, dims: int, channels: tuple[int, int, int], classes: int):
        super().__init__()
        c0, c1, c2 = channels
        self.stage0 = nn.Sequential(_block(dims, c0), _block(c0, c0))
        self.up1 = nn.Sequential(nn.ConvTranspose3d(c0, c1, 2, 2, bias=False), nn.BatchNorm3d(c1), nn.ReLU(inplace=True), _block(c1, c1))
        self.up2 = nn.ConvTranspose3d(c1, c2, 2, 2)
        self.point2 = nn.Conv3d(c2, c2, 1)
        self.classify = nn.ModuleList(nn.Conv3d(c, classes, 1) for c in channels)

    def coarse(self, x):
        """x: (B, C, X/4, Y/4, Z/4) -> features at 1/4 and 1/2."""
        f0 = self.stage0(x)
        return f0, self.up1(f0)

    def forward(self, x):
        f0, f1 = self.coarse(x)
        f2 = F.relu(self.point2(F.relu(self.up2(f1))))
        return [cls(f) for cls, f in zip(self.classify, (f0, f1, f2))]  # logits (B, K, X/s, Y/s, Z/s), s = 4, 2, 1

    def forward_at(self, x, index: torch.Tensor):
        """Logits at 1/4 and 1/2 (dense) and at full resolution for flat voxel indices (B, N) -> (B, K, N)."""
        f0, f1 = self.coarse(x)
        b, c1, x1, y1, z1 = f1.shape
        fy, fz = 2 * y1, 2 * z1
        i, j, k = index // (fy * fz), (index // fz) % fy, index % fz
        parent = ((i // 2) * y1 + j // 2) * z1 + k // 2  # (B, N) flat index at 1/2
        feat = torch.gather(f1.flatten(2), 2, parent[:, None].expand(b, c1, -1))  # (B, C1, N)
        # all 8 octants of the parent, then the voxel's own: gathering a kernel slice per voxel instead
        # makes the backward pass scatter N kernel slices into the kernel one by one
        c2 = self.up2.out_channels
        octants = torch.einsum("bcn,cdo->bodn", feat, self.up2.weight.flatten(2))  # (B, 8, C2, N)
        octant = ((i % 2) * 4 + (j % 2) * 2 + k % 2)[:, None, None].expand(b, 1, c2, -1)  # (B, 1, C2, N)
        f2 = torch.gather(octants, 1, octant)[:, 0] + self.up2.bias[None, :, None]  # (B, C2, N)
        f2 = F.relu(torch.einsum("bcn,dc->bdn", F.relu(f2), self.point2.weight[:, :, 0, 0, 0]) + self.point2.bias[None, :, None])
        cls = self.classify[2]
        return [self.classify[0](f0), self.classify[1](f1),
                torch.einsum("bcn,kc->bkn", f2, cls.weight[:, :, 0, 0, 0]) + cls.bias[None, :, None]]
