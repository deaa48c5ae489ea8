"""Int8 layers for CPU inference: 3x3x3 convolutions of uint8 activations by oneDNN's quantized primitive
(`torch.ops.onednn.qconv_pointwise`, the one PyTorch's own compiler lowers quantized models to), on VNNI or AMX
where the CPU has them. Without VNNI (AVX2), oneDNN sums pairs of uint8 x int8 products in 16 bits first, saturating
where both are large (two of 255 x 127 overflow): real activations rarely are, and on the benchmark's `validate`
this cost the shipped `tiny-lidar` less than weights of 7 bits (exact there) did, so the weights keep 8 bits on
every CPU (BENCHMARKS.md, "int8 on a CPU without VNNI").

Activations are uint8 with zero point 0 on a per-tensor scale (a calibrated range / 255:
`inference/calibration.py`), every one after a ReLU, so uint8's clamp at 0 is that ReLU; weights int8 per output
channel (max |w| / 127), batch norm folded in first (conv_norm.folded_norm). Volumes are z-outer (conv_norm.z_outer)
and convolved as their (B, C, Z, X, Y) views, channels-last: the layout oneDNN tiles best for a driving grid, whose z
is its shortest axis.

Most of a driving grid is empty: far from any occupied voxel every activation is one profile along z (the
background: a vector per z-layer, the grid's floor and top padded), and 8-bit rounding errs on it the same way
everywhere, a bias over the whole volume that moved labels more than the rounding noise elsewhere did. So each
residual sum adds an offset per z-layer and channel that gives the float32 sum's background (before its own
rounding), and the dequantized output another that gives it exactly (measured on an empty grid when the int8 layers
are made: `lidar.SSCNetEncoder.quantize`).

The packed weights are made when a model is put on an int8 path (`Co3SOP.use`) from the weights it has then: the
float layers' folded, or the int8 layers' own where a calibration carries them (fine-tuned through this arithmetic,
emulated by `fake_quantized` and `fake_int8_weight`: train/quantization_aware.py), which learnt the background's
rounding themselves and take no corrections.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from co3sop_nodes.kernels import quantized_add as add_kernel
from co3sop_nodes.model.conv_norm import folded_norm

_ZERO = torch.zeros(1, dtype=torch.long)


@dataclass(frozen=True)
class Int8Volume:
    """A quantized activation: values (B, C, Z, X, Y) uint8, channels-last in memory (a z-outer volume's view);
    value = values * scale."""

    values: torch.Tensor
    scale: float

    def dequantize(self, dtype: torch.dtype, offset: torch.Tensor | None = None) -> torch.Tensor:
        """(B, C, X, Y, Z) in `dtype`, channels-last in memory (as a 1x1 convolution reads it fast), plus `offset`
        (C, Z) where given: converted and laid out in one copy, then scaled and offset in place on contiguous
        memory."""
        b, c, z, x, y = self.values.shape
        out = torch.empty((b, c, x, y, z), dtype=dtype, memory_format=torch.channels_last_3d)
        out.copy_(self.values.permute(0, 1, 3, 4, 2)).mul_(self.scale)
        return out if offset is None else out.add_(offset.to(dtype)[:, None, None, :])


def onednn_int8() -> bool:
    """Whether this PyTorch build has oneDNN's quantized convolution and matrix product."""
    ops = ("qconv_prepack", "qconv_pointwise", "qlinear_prepack", "qlinear_pointwise")
    return torch.backends.mkldnn.is_available() and all(hasattr(torch.ops.onednn, op) for op in ops)


def available(channels: int) -> bool:
    """Whether this PyTorch build has oneDNN's int8 primitives and the residual sum's kernel compiles for
    `channels`."""
    return onednn_int8() and add_kernel.available(channels)


def int8_weight(weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """weight (Cout, ...) float -> its int8 values (contiguous, as the prepacks read them) and their scale per output
    channel (max |w| / 127), (Cout,)."""
    scale = _weight_scale(weight)
    return torch.round(weight / _per_row(scale, weight)).clamp_(-127, 127).to(torch.int8).contiguous(), scale


def _weight_scale(weight: torch.Tensor) -> torch.Tensor:
    """(Cout,) the int8 step of each output channel's weights: max |w| / 127."""
    return weight.detach().abs().flatten(1).amax(dim=1).clamp_min(1e-12) / 127


def _per_row(scale: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    return scale.view((-1,) + (1,) * (weight.dim() - 1))


def folded_conv(conv: nn.Conv3d, norm: nn.modules.batchnorm._BatchNorm) -> tuple[torch.Tensor, torch.Tensor]:
    """A Conv3d and its eval-mode batch norm as one convolution's float32 weights (Cout, Cin, kx, ky, kz) and bias
    (Cout,), detached."""
    factor, bias = folded_norm(norm, conv.bias)  # (Cout,) each
    weight = conv.weight * factor.view(-1, 1, 1, 1, 1)
    return weight.detach().float().contiguous(), bias.detach().float()


def fake_quantized(x: torch.Tensor, scale: float, zero: int = 0) -> torch.Tensor:
    """x rounded to uint8 steps of `scale` around the zero point `zero` (clamped to [-zero, 255 - zero] steps) and
    back, as an int8 layer's output (zero 0) or the head's signed input (zero 128) is: the emulation
    quantization-aware fine-tuning trains through, whose gradient passes the rounding unchanged (straight through)
    and stops where the clamp does."""
    q = x / scale
    return torch.clamp(q + (torch.round(q) - q).detach(), -zero, 255 - zero) * scale


def fake_int8_weight(weight: torch.Tensor) -> torch.Tensor:
    """weight (Cout, ...) rounded as `int8_weight` rounds it (per output channel, max |w| / 127) and back, with the
    rounding straight through for the gradient (the scale is taken as a constant)."""
    scale = _per_row(_weight_scale(weight), weight)
    q = weight / scale
    return torch.clamp(q + (torch.round(q) - q).detach(), -127, 127) * scale


class Int8Weights:
    """The int8 layers' own folded weights of a module an int8 path computes partly in int8, by its INT8_LAYERS'
    names: fine-tuned for the int8 arithmetic (train/quantization_aware.py), or None, the float layers' folded
    (`folded_int8_layers`, each module's own). A mixin of such an nn.Module; a checkpoint's int8 entry carries them
    (`Co3SOP.calibrate`)."""

    INT8_LAYERS: tuple[str, ...] = ()
    int8_weights: dict[str, tuple[torch.Tensor, torch.Tensor]] | None = None

    def folded_int8_layers(self) -> list[tuple[nn.Module, torch.Tensor, torch.Tensor]]:
        """Each of INT8_LAYERS: its layer (the geometry) and the float layers' weight and bias (Cout,) folded."""
        raise NotImplementedError

    def int8_layers(self) -> list[tuple[nn.Module, torch.Tensor, torch.Tensor]]:
        """Each of INT8_LAYERS: its layer (the geometry) and the folded weight, shaped as the layer's, and bias
        (Cout,) the int8 path computes it with: its own (`int8_weights`) or the float layers', folded."""
        folded = self.folded_int8_layers()
        if self.int8_weights is None:
            return folded
        return [(m, *self.int8_weights[name]) for (m, _, _), name in zip(folded, self.INT8_LAYERS)]

    def set_int8_weights(self, weights: dict[str, tuple[torch.Tensor, torch.Tensor]] | None) -> None:
        """The int8 layers' own folded (weight, bias) by INT8_LAYERS' names, each shaped as `folded_int8_layers`'
        (None: the float layers', folded); made into int8 layers at the next `quantize`."""
        if weights is not None:
            if sorted(weights) != sorted(self.INT8_LAYERS):
                raise ValueError(f"int8 weights of each of {', '.join(self.INT8_LAYERS)}, not {', '.join(weights)}")
            for (_, w, b), name in zip(self.folded_int8_layers(), self.INT8_LAYERS):
                weight, bias = weights[name]
                if weight.shape != w.shape or bias.shape != b.shape:
                    raise ValueError(
                        f"int8 weights of {name}: {tuple(weight.shape)} and {tuple(bias.shape)}, the layer's are "
                        f"{tuple(w.shape)} and {tuple(b.shape)}"
                    )
            weights = {n: (w.detach().float().clone(), b.detach().float().clone()) for n, (w, b) in weights.items()}
        self.int8_weights = weights


def _zxy(t: tuple[int, ...]) -> list[int]:
    return [t[2], t[0], t[1]]


class Int8ConvReLU:
    """relu(conv(x) + bias) of a Conv3d's geometry with the float weights (Cout, Cin, kx, ky, kz) and bias (Cout,)
    given, on Int8Volumes: the output quantized with `scale` (its calibrated range / 255); the input's zero point
    `in_zero` (0 after a ReLU). `folded` makes one of a Conv3d and its eval-mode batch norm. Not an nn.Module: its
    state is derived from the weights it was made of."""

    def __init__(
        self,
        conv: nn.Conv3d,
        weight: torch.Tensor,
        bias: torch.Tensor,
        in_scale: float,
        scale: float,
        in_zero: int = 0,
    ):
        weight = weight.detach().float().permute(0, 1, 4, 2, 3).contiguous()  # (Cout, Cin, kz, kx, ky): the views'
        q, self.w_scale = int8_weight(weight)
        self.stride, self.padding, self.dilation = _zxy(conv.stride), _zxy(conv.padding), _zxy(conv.dilation)
        self.groups, self.in_scale, self.in_zero, self.scale = conv.groups, in_scale, in_zero, scale
        self.bias = bias.detach().float()
        self.w_zero = _ZERO.expand(len(self.w_scale)).contiguous()  # symmetric weights
        self.packed = torch.ops.onednn.qconv_prepack(
            q, self.w_scale, in_scale, in_zero, self.stride, self.padding, self.dilation, self.groups, None
        )

    @classmethod
    def folded(
        cls, conv: nn.Conv3d, norm: nn.modules.batchnorm._BatchNorm, in_scale: float, scale: float, in_zero: int = 0
    ) -> Int8ConvReLU:
        """The layer of a Conv3d and its eval-mode batch norm, folded into one convolution (`folded_conv`)."""
        return cls(conv, *folded_conv(conv, norm), in_scale, scale, in_zero)

    def __call__(self, x: Int8Volume) -> Int8Volume:
        if x.scale != self.in_scale:
            raise ValueError(f"Int8ConvReLU: input scale {x.scale}, made for {self.in_scale}")
        y = torch.ops.onednn.qconv_pointwise(
            x.values, x.scale, self.in_zero, self.packed, self.w_scale, self.w_zero, self.bias,
            self.stride, self.padding, self.dilation, self.groups, self.scale, 0, None, "none", [], "",
        )  # fmt: skip
        return Int8Volume(y, self.scale)


class Int8LinearReLU:
    """relu(x @ weight.T + bias) of uint8 rows x (N, Cin) with `in_scale` (zero point 0), quantized with `scale`:
    int8 weights (Cout, Cin) per output channel. Not an nn.Module, as Int8ConvReLU."""

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor, in_scale: float, scale: float):
        q, self.w_scale = int8_weight(weight.detach().float())  # (Cout, Cin), (Cout,)
        self.in_scale, self.scale, self.bias = in_scale, scale, bias.detach().float()
        self.w_zero = _ZERO.expand(len(self.w_scale)).contiguous()
        self.packed = torch.ops.onednn.qlinear_prepack(q, None)

    def __call__(self, rows: torch.Tensor, in_scale: float) -> torch.Tensor:
        """rows (N, Cin) uint8 -> (N, Cout) uint8."""
        if in_scale != self.in_scale:
            raise ValueError(f"Int8LinearReLU: input scale {in_scale}, made for {self.in_scale}")
        return torch.ops.onednn.qlinear_pointwise(
            rows, in_scale, 0, self.packed, self.w_scale, self.w_zero, self.bias, self.scale, 0, None, "none", [], ""
        )


def add(a: Int8Volume, b: Int8Volume, scale: float, offset: torch.Tensor) -> Int8Volume:
    """a + b + offset (C, Z), quantized with `scale`: relu of it too, its terms being non-negative but for the
    background offset, which the clamp at 0 bounds."""
    threads = torch.get_num_threads()
    values = add_kernel.quantized_add(a.values, a.scale, b.values, b.scale, scale, offset / scale, threads)
    return Int8Volume(values, scale)


def centre(x: torch.Tensor) -> torch.Tensor:
    """A float volume (1, C, X, Y, Z)'s values (C, Z) at the centre of x and y."""
    return x[0, :, x.shape[2] // 2, x.shape[3] // 2, :].float()
