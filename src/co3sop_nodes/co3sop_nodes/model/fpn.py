"""Feature pyramid network: backbone stages 1..3 in, `levels` maps of one width out."""

from __future__ import annotations

import torch.nn.functional as F
from torch import nn


class FPN(nn.Module):
    """Top-down pathway over stages 1, 2, 3 (strides 8, 16, 32) plus extra stride-2 levels, as in SurroundOcc."""

    def __init__(self, in_channels: tuple[int, ...], channels: int, levels: int = 4):
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv2d(c, channels, 1) for c in in_channels)
        self.output = nn.ModuleList(nn.Conv2d(channels, channels, 3, padding=1) for _ in in_channels)
        self.extra = nn.ModuleList(nn.Conv2d(channels, channels, 3, 2, 1) for _ in range(levels - len(in_channels)))

    def forward(self, feats):  # [(B, C_i, H_i, W_i)] finest first
        lat = [conv(f) for conv, f in zip(self.lateral, feats)]
        for i in range(len(lat) - 1, 0, -1):
            lat[i - 1] = lat[i - 1] + F.interpolate(lat[i], size=lat[i - 1].shape[-2:], mode="nearest")
        outs = [conv(x) for conv, x in zip(self.output, lat)]
        for conv in self.extra:
            outs.append(conv(outs[-1]))
        return outs  # levels x (B, channels, H_l, W_l)
