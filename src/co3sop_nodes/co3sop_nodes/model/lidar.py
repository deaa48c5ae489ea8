"""LiDAR vehicle halves (the cheap modality): LMSCNet- and SSCNet-style encoders of a voxelised scan.

Input: the scan voxelised on the label grid, (B, 1, X, Y, Z) occupancy. Output:
the same (B, C, X/4, Y/4, Z/4) feature volume the camera half produces, so the
ego fuses either modality.
- LMSCNet style: height slices as channels of a 2D UNet-like encoder over the
  bird's-eye view, folded back into (C, Z/4) at 1/4 resolution.
- SSCNet style: 3D convolutions, two stride-2 reductions, then dilated 3D
  residual blocks for a large receptive field; on an int8 path, with a
  calibration, every 3D layer after the first computes in int8 (quantized.py),
  on weights of its own where the calibration carries them (fine-tuned through
  the int8 arithmetic: train/quantization_aware.py).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from co3sop_nodes.kernels import occupancy_conv as occupancy_kernel
from co3sop_nodes.model import quantized
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


class SSCNetEncoder(quantized.Int8Weights, nn.Module):
    # the activations an int8 path quantizes, each after a ReLU: the output of each 3x3x3 layer and each residual sum
    ACTIVATIONS = ("down.0", "down.1", "dilated.0", "sum.0", "dilated.1", "sum.1", "dilated.2", "sum.2")
    STEPS = (255.0,) * len(ACTIVATIONS)  # the quantization steps of each one's range (uint8, zero point 0)
    INT8_LAYERS = ("down.1", "dilated.0", "dilated.1", "dilated.2")  # the layers an int8 path computes in int8

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
        # each ACTIVATIONS' calibrated range (0: none), loaded from a checkpoint's int8 entry (`Co3SOP.calibrate`)
        self.register_buffer("int8_ranges", torch.zeros(len(self.ACTIVATIONS)), persistent=False)
        self._int8: list[quantized.Int8ConvReLU] | None = None  # made by `quantize`
        self._offsets: list[torch.Tensor] = []  # the int8 layers' background corrections (`quantize`)
        self._scales: list[float] = []  # each ACTIVATIONS' quantization step on the int8 path (`quantize`)

    @property
    def calibrated(self) -> bool:
        return bool((self.int8_ranges > 0).all())

    def folded_int8_layers(self) -> list[tuple[nn.Conv3d, torch.Tensor, torch.Tensor]]:
        """Each of INT8_LAYERS: its convolution and the float layer's weights (Cout, Cin, 3, 3, 3) and bias (Cout,)
        with its batch norm folded in."""
        return [(m[0], *quantized.folded_conv(m[0], m[1])) for m in (self.down[1], *self.dilated)]

    def quantize(self, height: int) -> bool:
        """Make the int8 layers from the weights and ranges as they are now, for scans `height` voxels high (or none,
        where the model has no calibration or the machine cannot run them); whether there are some. Fine-tuned
        int8 weights learnt the background's rounding themselves: the background corrections are then zero."""
        c = self.down[0][0].out_channels
        self._int8 = None
        if self.calibrated and quantized.available(2 * c) and occupancy_kernel.available(c, torch.uint8):
            self._scales = s = self._step_sizes()
            ins = [s[0], s[1], s[3], s[5]]  # each layer's input: the first layer's, down.1's, then the sums
            outs = [s[1], s[2], s[4], s[6]]
            self._int8 = [quantized.Int8ConvReLU(*m, a, b) for m, a, b in zip(self.int8_layers(), ins, outs)]
            zero = [torch.zeros(2 * c, height // 4) for _ in range(len(self.dilated) + 1)]  # (C, Z/4) each
            self._offsets = zero if self.int8_weights is not None else self._background_offsets(height)
        return self._int8 is not None

    def int8_emulated(self, occupancy, layers: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
        """The int8 path's forward emulated in float32 on folded (weight, bias) of each of INT8_LAYERS: weights
        and activations rounded to its int8 and uint8 steps, straight through for the gradients (no background
        corrections), (B, C, X/4, Y/4, Z/4). What quantization-aware fine-tuning trains `layers` through."""
        s = self._step_sizes()
        convs = [self.down[1][0], *(m[0] for m in self.dilated)]

        def layer(i, x):
            conv, (weight, bias) = convs[i], layers[i]
            return F.relu(
                F.conv3d(x, quantized.fake_int8_weight(weight), bias, conv.stride, conv.padding, conv.dilation)
            )

        with torch.no_grad():  # the first layer stays the float model's (the compiled kernel rounds its output)
            first = quantized.fake_quantized(self.down[0](occupancy.float()), s[0])
        f = quantized.fake_quantized(layer(0, first), s[1])
        for i in range(len(self.dilated)):
            y = quantized.fake_quantized(layer(1 + i, f), s[2 + 2 * i])
            f = quantized.fake_quantized(F.relu(f + y), s[3 + 2 * i])
        return F.conv3d(f, self.out.weight.detach(), self.out.bias.detach())  # the float model's output layer

    def _step_sizes(self) -> list[float]:
        """Each of ACTIVATIONS' quantization step: its calibrated range / 255."""
        if not self.calibrated:
            raise ValueError("the int8 path needs a calibration: this encoder has none")
        return (self.int8_ranges / 255).tolist()

    @torch.no_grad()
    def _background_offsets(self, height: int) -> list[torch.Tensor]:
        """The int8 path's background corrections (quantized.py), each (C, Z/4): one per residual sum, then the
        output's; measured on an empty grid `height` voxels high and wide enough that its centre is out of reach of
        its sides, the float32 layers against the int8 ones, each correction measured with those before it in place."""
        empty = torch.zeros(1, 1, 128, 128, height, dtype=torch.uint8)
        exact = [quantized.centre(a) for a in self.activations(empty)]  # float32, in ACTIVATIONS' order
        offsets = []
        for i in range(len(self.dilated)):
            f, y = self._int8_layers(empty, offsets, until=i)  # sum i's terms: its value before rounding wanted
            before = quantized.centre(f.dequantize(torch.float32)) + quantized.centre(y.dequantize(torch.float32))
            offsets.append(exact[3 + 2 * i] - before)
        f = self._int8_layers(empty, offsets)
        return [*offsets, exact[-1] - quantized.centre(f.dequantize(torch.float32))]

    def _int8_layers(self, occupancy, offsets: list[torch.Tensor], until: int | None = None):
        """The int8 layers on occupancy, with the residual sums' background `offsets`: the last sum, an Int8Volume;
        with `until`, the input of dilated layer `until` and that layer's output instead."""
        s = self._scales
        first = self._first(occupancy, s[0])  # (B, C/2, X/2, Y/2, Z/2) z-outer uint8
        f = self._int8[0](quantized.Int8Volume(first.permute(0, 1, 4, 2, 3), s[0]))  # (B, C, Z/4, X/4, Y/4) views
        for i, layer in enumerate(self._int8[1:]):
            y = layer(f)
            if i == until:
                return f, y
            f = quantized.add(f, y, s[3 + 2 * i], offsets[i])
        return f

    def forward(self, occupancy):  # (B, 1, X, Y, Z) 0/1
        last = self.int8_volume(occupancy)
        if last is not None:  # the 1x1 output layer in the path's float precision
            dtype = torch.get_autocast_dtype("cpu") if torch.is_autocast_enabled("cpu") else torch.float32
            return self.out(last.dequantize(dtype, self.output_offset))  # (B, C, X/4, Y/4, Z/4)
        f = self.down[1](self._first(occupancy)) if self._first_compiled(occupancy) else self.down(occupancy.float())
        reduced = self.path.reduced
        if reduced:  # the dilated 3x3x3 layers run 1.5-2x as fast on z-outer volumes (conv_norm): no copy if it is one
            f = z_outer(f)
        for layer in self.dilated:
            f = F.relu(f + layer(f))  # z-outer in, z-outer out
        if reduced:  # back to channels-last for the 1x1 convolutions, slow on z-outer volumes
            f = f.contiguous(memory_format=torch.channels_last_3d)
        return self.out(f)  # (B, C, X/4, Y/4, Z/4)

    def int8_volume(self, occupancy) -> quantized.Int8Volume | None:
        """The int8 layers' last volume (B, C, Z/4, X/4, Y/4) for a scan, where this path computes them (an int8 path
        with the layers made, a scan as the nodes voxelise it), before the 1x1 output layer; None elsewhere."""
        if not (self.path.int8 and self._int8 is not None and self._first_compiled(occupancy)):
            return None
        if occupancy.shape[-1] != 4 * self._offsets[-1].shape[-1]:
            raise ValueError(f"int8 layers made for scans {4 * self._offsets[-1].shape[-1]} voxels high")
        return self._int8_layers(occupancy, self._offsets)

    @property
    def output_offset(self) -> torch.Tensor | None:
        """The background correction (C, Z/4) the int8 volume's dequantization adds; none for fine-tuned int8 weights,
        which learnt the background's rounding themselves."""
        return None if self.int8_weights is not None else self._offsets[-1]

    @torch.no_grad()
    def activations(self, occupancy) -> list[torch.Tensor]:
        """The float32 forward's ACTIVATIONS for occupancy (B, 1, X, Y, Z), as the int8 path quantizes them: what a
        calibration measures."""
        out = [self.down[0](occupancy.float())]
        out.append(self.down[1](out[-1]))
        for layer in self.dilated:
            out.append(layer(out[-1]))
            out.append(F.relu(out[-2] + out[-1]))
        return out

    def _first_compiled(self, occupancy) -> bool:
        """Whether the first layer runs as the compiled kernel: on a reduced-precision CPU path, for a scan as the
        nodes voxelise it (uint8 or bool)."""
        return (
            self.path.reduced
            and self.path.kernels(occupancy)
            and occupancy.dtype in (torch.uint8, torch.bool)
            and occupancy_kernel.available(self.down[0][0].out_channels, self.first_dtype)
        )

    @property
    def first_dtype(self) -> torch.dtype:
        """What the compiled first layer writes: uint8 for the int8 layers, bfloat16 on a bfloat16 path (float32 for
        autocast to take from there otherwise)."""
        if self.path.int8 and self._int8 is not None:
            return torch.uint8
        return torch.bfloat16 if self.path.floats == "bfloat16" else torch.float32

    def _first(self, occupancy, scale: float = 1.0):
        """The first layer (convolution, batch norm folded into it, ReLU) by the compiled kernel: (B, C/2, X/2, Y/2,
        Z/2) z-outer (the stride-2 layer after it runs faster on such volumes, and leaves them so for the dilated
        ones), in `first_dtype` (uint8: quantized with `scale`)."""
        conv, norm = self.down[0][0], self.down[0][1]
        factor, shift = folded_norm(norm, conv.bias)  # (C/2,)
        weight = conv.weight * factor.view(-1, 1, 1, 1, 1)  # (C/2, 1, 3, 3, 3)
        threads = torch.get_num_threads()
        return occupancy_kernel.occupancy_conv_relu(occupancy, weight, shift, self.first_dtype, threads, True, scale)
