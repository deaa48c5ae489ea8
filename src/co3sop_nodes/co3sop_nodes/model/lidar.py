"""LiDAR vehicle halves (the cheap modality): LMSCNet- and SSCNet-style encoders of a voxelised scan.

Input: the scan voxelised on the label grid, (B, 1, X, Y, Z) occupancy. Output:
the same (B, C, X/4, Y/4, Z/4) feature volume the camera half produces, so the
ego fuses either modality.
- LMSCNet style: height slices as channels of a 2D UNet-like encoder over the
  bird's-eye view, folded back into (C, Z/4) at 1/4 resolution.
- SSCNet style: 3D convolutions, two stride-2 reductions, then dilated 3D
  residual blocks for a large receptive field.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import nn

from co3sop_nodes.model.conv_norm import ConvNorm


class LMSCNetEncoder(nn.Module):
    def __init__(self, height: int, dims: int, channels: int):
        super().__init__()
        self.dims, self.z = dims, height // 4
        c = channels

        def block(cin, cout, stride):
            return ConvNorm(
                nn.Conv2d(cin, cout, 3, stride, 1),
                nn.BatchNorm2d(cout),
                nn.ReLU(inplace=True),
                nn.Conv2d(cout, cout, 3, 1, 1),
                nn.BatchNorm2d(cout),
                nn.ReLU(inplace=True),
            )

        self.enc = nn.Sequential(block(height, c, 1), block(c, 2 * c, 2), block(2 * c, 4 * c, 2))
        self.out = nn.Conv2d(4 * c, dims * self.z, 1)

    def forward(self, occupancy):  # (B, 1, X, Y, Z)
        b, _, x, y, z = occupancy.shape
        bev = occupancy[:, 0].permute(0, 3, 1, 2)  # (B, Z, X, Y): heights as channels
        f = self.out(self.enc(bev))  # (B, C * Z/4, X/4, Y/4)
        return f.view(b, self.dims, self.z, x // 4, y // 4).permute(0, 1, 3, 4, 2)  # (B, C, X/4, Y/4, Z/4)


class SSCNetEncoder(nn.Module):
    def __init__(self, dims: int, channels: int):
        super().__init__()
        c = channels

        def conv(cin, cout, stride=1, dilation=1):
            return ConvNorm(
                nn.Conv3d(cin, cout, 3, stride, dilation, dilation), nn.BatchNorm3d(cout), nn.ReLU(inplace=True)
            )

        self.down = nn.Sequential(conv(1, c // 2, 2), conv(c // 2, c, 2))
        self.dilated = nn.ModuleList([conv(c, c, 1, 2), conv(c, c, 1, 2), conv(c, c, 1, 3)])
        self.out = nn.Conv3d(c, dims, 1)

    def forward(self, occupancy):  # (B, 1, X, Y, Z)
        f = self.down(occupancy)
        for layer in self.dilated:
            f = F.relu(f + layer(f))
        return self.out(f)  # (B, C, X/4, Y/4, Z/4)
