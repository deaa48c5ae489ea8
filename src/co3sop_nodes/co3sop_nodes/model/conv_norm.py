"""Convolutions followed by batch norm, folded into one convolution on a reduced-precision inference path.

In eval mode batch norm is an affine map per channel, so conv then norm is one convolution with scaled weights
and a bias. Under autocast the convolution runs in bfloat16 or float16 and batch norm in float32: unfolded,
every norm costs two copies of its activation between the precisions (a fifth of the LiDAR vehicle half's time
on the CPU) besides the norm itself. Float32 and training keep the layers as they are, so float32 inference
stays bit for bit what it was; the folded weights are computed at each call (a few thousand values) and never
stored, so the module's state is the plain layers' and `Co3SOP.use` may switch paths at any time.

On the CPU a folded convolution followed by its ReLU runs as one oneDNN primitive with the ReLU fused
(`torch.ops.mkldnn._convolution_pointwise`, which PyTorch's own compiler uses for CPU inference): the same values,
bit for bit (tested), one pass over the output fewer.

A folded 3D convolution keeps its input's memory layout, channels-last or `z_outer` (channels-last with z the
outermost spatial axis): oneDNN's kernels tile the innermost spatial axis, and a driving grid's z is its
shortest (6 or 12 voxels against 64 or 128 along y in the head of `tiny-lidar`), so the head's 3x3x3 layers run
1.25-1.4x as fast on z-outer volumes on the CPU, and the LiDAR vehicle half's dilated ones 1.5-2x (bench_model.py
--roofline).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from co3sop_nodes.model.path import InferencePath, onednn

_CONVS = (nn.Conv2d, nn.Conv3d)


class ConvNorm(nn.Sequential):
    """An nn.Sequential (same layers, same state_dict) whose every convolution directly followed by batch norm runs
    as one folded convolution on a reduced-precision inference path."""

    def __init__(self, *layers: nn.Module):
        super().__init__(*layers)
        self.path = InferencePath()  # set by Co3SOP.use

    def forward(self, x):
        if self.training or not self.path.reduced:
            return super().forward(x)
        layers = list(self)
        i = 0
        while i < len(layers):
            layer = layers[i]
            norm = layers[i + 1] if i + 1 < len(layers) else None
            if isinstance(layer, _CONVS) and isinstance(norm, nn.modules.batchnorm._BatchNorm):
                relu = i + 2 < len(layers) and isinstance(layers[i + 2], nn.ReLU) and self.path.kernels(x)
                x = folded(layer, norm, x, relu)
                i += 3 if relu else 2
            else:
                x = layer(x)
                i += 1
        return x


def folded_norm(norm: nn.modules.batchnorm._BatchNorm, bias: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """norm(y + bias) in eval mode as scale * y + shift, per channel: (scale, shift), both (C,)."""
    scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)  # (C,)
    shift = norm.bias - norm.running_mean * scale
    if bias is not None:
        shift = shift + bias * scale
    return scale, shift


def z_outer(x: torch.Tensor) -> torch.Tensor:
    """x (B, C, X, Y, Z) -> the same tensor stored (B, Z, X, Y, C) in memory (a copy unless it already is)."""
    return x.permute(0, 1, 4, 2, 3).contiguous(memory_format=torch.channels_last_3d).permute(0, 1, 3, 4, 2)


def is_z_outer(x: torch.Tensor) -> bool:
    return x.dim() == 5 and x.permute(0, 1, 4, 2, 3).is_contiguous(memory_format=torch.channels_last_3d)


def _zxy(t: tuple[int, int, int]) -> tuple[int, int, int]:
    return t[2], t[0], t[1]


def folded(
    conv: nn.Conv2d | nn.Conv3d, norm: nn.modules.batchnorm._BatchNorm, x: torch.Tensor, relu: bool = False
) -> torch.Tensor:
    """norm(conv(x)) in eval mode as one convolution: weights scaled per output channel, the norm's shift a bias;
    with `relu`, relu of that (fused into the convolution on the CPU where oneDNN's primitive takes it). A z-outer
    x (B, C, X, Y, Z) gives a z-outer result: the convolution runs on the (B, C, Z, X, Y) views."""
    scale, shift = folded_norm(norm, conv.bias)  # (Cout,)
    weight = conv.weight * scale.view(-1, *[1] * (conv.weight.dim() - 1))  # keeps the weight's memory format
    plain = conv.padding_mode == "zeros" and not isinstance(conv.padding, str)
    stride, padding, dilation = conv.stride, conv.padding, conv.dilation
    z = isinstance(conv, nn.Conv3d) and plain and is_z_outer(x)
    if z:  # (B, C, Z, X, Y) views
        x, weight = x.permute(0, 1, 4, 2, 3), weight.permute(0, 1, 4, 2, 3)
        stride, padding, dilation = _zxy(stride), _zxy(padding), _zxy(dilation)
    # autocast's casts, as the convolution it replaces takes them
    dtype = torch.get_autocast_dtype("cpu") if torch.is_autocast_enabled("cpu") else x.dtype
    if relu and plain and x.device.type == "cpu" and onednn(dtype):
        y = torch.ops.mkldnn._convolution_pointwise(
            x.to(dtype), weight.to(dtype), shift.to(dtype), padding, stride, dilation, conv.groups, "relu", [None], None
        )
    else:
        y = (
            F.conv3d(x, weight, shift, stride, padding, dilation, conv.groups)
            if z
            else conv._conv_forward(x, weight, shift)
        )
        y = y.relu_() if relu else y
    return y.permute(0, 1, 3, 4, 2) if z else y  # (B, Cout, X', Y', Z')
