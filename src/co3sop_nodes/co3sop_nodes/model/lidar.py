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

import torch
import torch.nn.functional as F
from torch import nn

from co3sop_nodes.kernels import occupancy_conv as occupancy_kernel
from co3sop_nodes.model.conv_norm import ConvNorm, folded_norm, z_outer
from co3sop_nodes.model.path import InferencePath


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

    def forward(self, occupancy):  # (B, 1, X, Y, Z) 0/1
        b, _, x, y, z = occupancy.shape
        bev = occupancy[:, 0].float().permute(0, 3, 1, 2)  # (B, Z, X, Y): heights as channels
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
        self.path = InferencePath()  # set by Co3SOP.use

    def forward(self, occupancy):  # (B, 1, X, Y, Z) 0/1
        f = self.down[1](self._first(occupancy)) if self._first_compiled(occupancy) else self.down(occupancy.float())
        reduced = self.path.reduced
        if reduced:  # the dilated 3x3x3 layers run 1.5-2x as fast on z-outer volumes (conv_norm): no copy if it is one
            f = z_outer(f)
        for layer in self.dilated:
            f = F.relu(f + layer(f))  # z-outer in, z-outer out
        if reduced:  # back to channels-last for the 1x1 convolutions, slow on z-outer volumes
            f = f.contiguous(memory_format=torch.channels_last_3d)
        return self.out(f)  # (B, C, X/4, Y/4, Z/4)

    def _first_compiled(self, occupancy) -> bool:
        """Whether the first layer runs as the compiled kernel: on a reduced-precision CPU path, for a scan as the
        nodes voxelise it (uint8 or bool)."""
        return (
            self.path.reduced
            and self.path.kernels(occupancy)
            and occupancy.dtype in (torch.uint8, torch.bool)
            and occupancy_kernel.available(self.down[0][0].out_channels, self.path.precision == "bfloat16")
        )

    def _first(self, occupancy):
        """The first layer (convolution, batch norm folded into it, ReLU) by the compiled kernel: (B, C/2, X/2, Y/2,
        Z/2) z-outer (the stride-2 layer after it runs faster on such volumes, and leaves them so for the dilated
        ones), in bfloat16 on a bfloat16 path (float32 for autocast to take from there otherwise)."""
        conv, norm = self.down[0][0], self.down[0][1]
        scale, shift = folded_norm(norm, conv.bias)  # (C/2,)
        weight = conv.weight * scale.view(-1, 1, 1, 1, 1)  # (C/2, 1, 3, 3, 3)
        bfloat16 = self.path.precision == "bfloat16"
        threads = torch.get_num_threads()
        return occupancy_kernel.occupancy_conv_relu(occupancy, weight, shift, bfloat16, threads, z_outer=True)
