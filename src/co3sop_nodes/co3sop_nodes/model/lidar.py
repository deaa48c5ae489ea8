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
from co3sop_nodes.model.conv_norm import ConvNorm, folded_norm
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
        phases = self.path.reduced and self.path.kernels(f)
        for layer in self.dilated:
            f = F.relu(f + (phase_conv_relu(layer, f) if phases and thin(layer, f) else layer(f)))
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
        Z/2) channels-last, in bfloat16 on a bfloat16 path (float32 for autocast to take from there otherwise)."""
        conv, norm = self.down[0][0], self.down[0][1]
        scale, shift = folded_norm(norm, conv.bias)  # (C/2,)
        weight = conv.weight * scale.view(-1, 1, 1, 1, 1)  # (C/2, 1, 3, 3, 3)
        bfloat16 = self.path.precision == "bfloat16"
        return occupancy_kernel.occupancy_conv_relu(occupancy, weight, shift, bfloat16, torch.get_num_threads())


def thin(layer: ConvNorm, x: torch.Tensor) -> bool:
    """Whether `phase_conv_relu` takes the dilated layer over x (B, C, X, Y, Z): z holds at most 3 of its taps' steps
    (Z / dilation), so the 2D convolution's blocks are mostly taps, not zeros."""
    d = layer[0].dilation[2]
    return -(-x.shape[4] // d) <= 3


def phase_conv_relu(layer: ConvNorm, x: torch.Tensor) -> torch.Tensor:
    """relu(norm(conv(x))) of a dilated 3x3x3 layer (conv, batch norm, ReLU; stride 1, padding = dilation d) as a 2D
    convolution, on a reduced-precision path: x (B, C, X, Y, Z) -> (B, C, X, Y, Z), channels-last in memory.

    Along z the layer only couples voxels d apart, z = m d + r: each phase r is an independent column of M = Z / d
    voxels (z padded with zeros to a multiple of d) with taps m - 1, m, m + 1. Stacking m into the channels makes
    the layer a dilated 3x3 2D convolution over (X, Y) per phase, M C -> M C channels, whose (m_out, m_in) block is
    the z-tap m_in - m_out + 1 (zero beyond one step). On a thin volume (M <= 3) that skips the taps that fall in
    z's padding (a third of them at d = 3 over 6 voxels) and takes oneDNN's 2D kernels, faster than its 3D ones.
    Sums in another order than the 3D convolution's: reduced-precision paths only, within their tolerance."""
    conv, norm = layer[0], layer[1]
    b, c, nx, ny, nz = x.shape
    d = conv.dilation[2]
    m = -(-nz // d)
    scale, shift = folded_norm(norm, conv.bias)  # (C,)
    w = conv.weight * scale.view(-1, 1, 1, 1, 1)  # (C, C, 3, 3, 3)
    zero = w.new_zeros(c, c, 3, 3)
    weight = torch.cat(
        [torch.cat([w[..., i - o + 1] if abs(i - o) <= 1 else zero for i in range(m)], 1) for o in range(m)]
    )  # (M C, M C, 3, 3): output phase-row blocks o, input blocks i
    v = x.permute(0, 2, 3, 4, 1)  # (B, X, Y, Z, C)
    if m * d != nz:
        v = F.pad(v, (0, 0, 0, m * d - nz))
    v = v.reshape(b, nx, ny, m, d, c).permute(0, 4, 1, 2, 3, 5).reshape(b * d, nx, ny, m * c)  # (B d, X, Y, M C)
    y = F.conv2d(v.permute(0, 3, 1, 2), weight, shift.repeat(m), 1, (d, d), (d, d)).relu_()  # (B d, M C, X, Y)
    y = y.permute(0, 2, 3, 1).reshape(b, d, nx, ny, m, c).permute(0, 2, 3, 4, 1, 5).reshape(b, nx, ny, m * d, c)
    return y[:, :, :, :nz].permute(0, 4, 1, 2, 3).contiguous(memory_format=torch.channels_last_3d)  # no copy unpadded
