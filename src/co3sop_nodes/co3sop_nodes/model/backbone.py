"""ResNet image backbone in plain PyTorch, with optional modulated deformable convolution (DCNv2).

There is no CPU torchvision here, so the ResNet family is written out: basic
blocks (ResNet-18/34) or bottlenecks (ResNet-50/101), stride-2 stages, and in
the stages the config names, 3x3 convolutions replaced by deformable ones
(the paper's ResNet101-DCN). The deformable convolution samples its input with
`grid_sample`; `deform_conv2d_reference` is the direct, loop-based definition
the fast path is tested against.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from co3sop_nodes.model.config import BackboneConfig


def deform_conv2d(x, offset, mask, weight, bias, stride: int = 1, padding: int = 1):
    """Modulated deformable 3x3 (any k) convolution via bilinear grid sampling.

    x: (B, Cin, H, W); offset: (B, 2K, Ho, Wo) as (dy, dx) per tap; mask: (B, K, Ho, Wo);
    weight: (Cout, Cin, kh, kw). Returns (B, Cout, Ho, Wo).
    """
    b, cin, h, w = x.shape
    cout, _, kh, kw = weight.shape
    ho, wo = offset.shape[-2:]
    k = kh * kw
    ky, kx = torch.meshgrid(torch.arange(kh, device=x.device), torch.arange(kw, device=x.device), indexing="ij")
    oy, ox = torch.meshgrid(torch.arange(ho, device=x.device), torch.arange(wo, device=x.device), indexing="ij")
    # sampling positions (B, K, Ho, Wo) in input pixels
    base_y = (oy * stride - padding)[None, None] + ky.reshape(1, k, 1, 1)
    base_x = (ox * stride - padding)[None, None] + kx.reshape(1, k, 1, 1)
    off = offset.view(b, k, 2, ho, wo)
    py = base_y + off[:, :, 0]
    px = base_x + off[:, :, 1]
    grid = torch.stack(
        [2 * (px + 0.5) / w - 1, 2 * (py + 0.5) / h - 1], dim=-1
    )  # (B, K, Ho, Wo, 2), align_corners=False
    sampled = F.grid_sample(x, grid.view(b, k * ho, wo, 2), mode="bilinear", padding_mode="zeros", align_corners=False)
    sampled = sampled.view(b, cin, k, ho, wo) * mask.view(b, 1, k, ho, wo)  # (B, Cin, K, Ho, Wo)
    out = torch.einsum("bckhw,ock->bohw", sampled, weight.view(cout, cin, k))
    return out if bias is None else out + bias.view(1, -1, 1, 1)


def deform_conv2d_reference(x, offset, mask, weight, bias, stride: int = 1, padding: int = 1):
    """The definition, one output value at a time (slow; for tests)."""
    b, cin, h, w = x.shape
    cout, _, kh, kw = weight.shape
    ho, wo = offset.shape[-2:]
    out = torch.zeros(b, cout, ho, wo, dtype=x.dtype)

    def pixel(n, c, y, xx):
        return x[n, c, y, xx] if 0 <= y < h and 0 <= xx < w else x.new_zeros(())

    for n in range(b):
        for i in range(ho):
            for j in range(wo):
                acc = torch.zeros(cout, dtype=x.dtype)
                for t in range(kh * kw):
                    dy, dx = offset[n, 2 * t, i, j], offset[n, 2 * t + 1, i, j]
                    py = i * stride - padding + t // kw + dy
                    px = j * stride - padding + t % kw + dx
                    y0, x0 = math.floor(py), math.floor(px)
                    ly, lx = py - y0, px - x0
                    for c in range(cin):
                        v = (
                            (1 - ly) * (1 - lx) * pixel(n, c, y0, x0)
                            + (1 - ly) * lx * pixel(n, c, y0, x0 + 1)
                            + ly * (1 - lx) * pixel(n, c, y0 + 1, x0)
                            + ly * lx * pixel(n, c, y0 + 1, x0 + 1)
                        )
                        acc = acc + weight[:, c, t // kw, t % kw] * v * mask[n, t, i, j]
                out[n, :, i, j] = acc + (0 if bias is None else bias)
    return out


class DeformConv2d(nn.Module):
    """3x3 modulated deformable convolution; offsets and masks predicted by a zero-initialised conv."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.stride = stride
        self.weight = nn.Parameter(torch.empty(cout, cin, 3, 3))
        nn.init.kaiming_normal_(self.weight, mode="fan_out", nonlinearity="relu")
        self.offset = nn.Conv2d(cin, 27, 3, stride, 1)  # 18 offsets + 9 masks
        nn.init.zeros_(self.offset.weight)
        nn.init.zeros_(self.offset.bias)  # starts as a plain conv (mask 0.5 everywhere: sigmoid(0))

    def forward(self, x):
        o = self.offset(x)
        return deform_conv2d(x, o[:, :18], torch.sigmoid(o[:, 18:]) * 2, self.weight, None, self.stride, 1)


def _conv3(cin: int, cout: int, stride: int, deform: bool) -> nn.Module:
    return DeformConv2d(cin, cout, stride) if deform else nn.Conv2d(cin, cout, 3, stride, 1, bias=False)


class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int, deform: bool):
        super().__init__()
        self.conv1, self.bn1 = _conv3(cin, cout, stride, deform), nn.BatchNorm2d(cout)
        self.conv2, self.bn2 = _conv3(cout, cout, 1, deform), nn.BatchNorm2d(cout)
        self.skip = (
            nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
            if stride != 1 or cin != cout
            else nn.Identity()
        )

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(y)) + self.skip(x))


class Bottleneck(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int, deform: bool):
        super().__init__()
        mid = cout // 4
        self.conv1, self.bn1 = nn.Conv2d(cin, mid, 1, bias=False), nn.BatchNorm2d(mid)
        self.conv2, self.bn2 = _conv3(mid, mid, stride, deform), nn.BatchNorm2d(mid)
        self.conv3, self.bn3 = nn.Conv2d(mid, cout, 1, bias=False), nn.BatchNorm2d(cout)
        self.skip = (
            nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
            if stride != 1 or cin != cout
            else nn.Identity()
        )

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)))
        y = F.relu(self.bn2(self.conv2(y)))
        return F.relu(self.bn3(self.conv3(y)) + self.skip(x))


class ResNet(nn.Module):
    """Returns the outputs of every stage: strides 4, 8, 16, 32."""

    def __init__(self, cfg: BackboneConfig):
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(3, cfg.stem, 7, 2, 3, bias=False),
            nn.BatchNorm2d(cfg.stem),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, 2, 1),
        )
        block = Bottleneck if cfg.bottleneck else BasicBlock
        stages, cin = [], cfg.stem
        for i, (n, cout, deform) in enumerate(zip(cfg.depth, cfg.channels, cfg.deform_stages)):
            layers = [
                block(cin if j == 0 else cout, cout, (1 if i == 0 else 2) if j == 0 else 1, deform) for j in range(n)
            ]
            stages.append(nn.Sequential(*layers))
            cin = cout
        self.stages = nn.ModuleList(stages)

    def forward(self, x):  # x: (B, 3, H, W)
        feats, y = [], self.stem(x)
        for stage in self.stages:
            y = stage(y)
            feats.append(y)
        return feats  # [(B, C_i, H / 2^(i+2), W / 2^(i+2))]
