"""Prediction head: 3D convolutions and transposed convolutions to logits at 1/4, 1/2 and full resolution.

Full resolution holds 64x the voxels of 1/4, so it gets only a stride-2
transposed convolution (each fine voxel reads one coarse voxel) and pointwise
layers, without batch norm: a fine voxel's logits then depend on its parent
voxel alone, and `forward_at` evaluates them for chosen voxels only, exactly
as the dense pass would (training samples voxels there; tests check equality),
and `labels` computes inference's labels and confidence per parent voxel in
cache-sized chunks, never holding the dense full-resolution logits nor
computing the 1/4 and 1/2 logits (the dense pass is its reference). On the
CPU that last stage runs as a compiled kernel (`octant_kernel`) where a C
compiler is available, about 10x faster than its PyTorch loop, tested equal.

On an int8 path, once calibrated, the layers up to the 1/2 features compute in int8 (quantized.py): the fused
features quantized symmetrically (zero point 128: they are signed), the 3x3x3 layers and the transposed
convolution to 1/2 (one matrix product per coarse voxel) on oneDNN's int8 primitives, each output uint8 after its
ReLU; the last stage reads those uint8 features as they are. Those layers are 80 % of the head's operations. Their
weights are the float layers', folded, or their own where a calibration carries them (`calibrate --fine-tune`:
trained through the emulated int8 arithmetic, `int8_emulated`, on the features int8 vehicles send, toward the float
model's labels: train/quantization_aware.py).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from co3sop_nodes.kernels import octant as octant_kernel
from co3sop_nodes.kernels import quantize_volume as quantize_kernel
from co3sop_nodes.model import quantized
from co3sop_nodes.model.conv_norm import ConvNorm, folded_norm, z_outer
from co3sop_nodes.model.path import InferencePath


def _block(cin: int, cout: int) -> ConvNorm:
    return ConvNorm(nn.Conv3d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm3d(cout), nn.ReLU(inplace=True))


def _batched(pairs: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample (labels, confidence) as (B, ...) batches: a batch of one (a node's frame) as views, not copies."""
    if len(pairs) == 1:
        return pairs[0][0][None], pairs[0][1][None]
    return torch.stack([p[0] for p in pairs]), torch.stack([p[1] for p in pairs])


class OccupancyHead(quantized.Int8Weights, nn.Module):
    # the activations an int8 path quantizes: the fused features (signed), then each layer's output after its ReLU
    ACTIVATIONS = ("input", "stage0.0", "stage0.1", "up1", "up1.3")
    # the quantization steps of each activation's range: the input's spans [-range, range]
    STEPS = (127.5, 255.0, 255.0, 255.0, 255.0)
    INT8_LAYERS = ("stage0.0", "stage0.1", "up1.0", "up1.3")  # the layers an int8 path computes in int8

    def __init__(self, dims: int, channels: tuple[int, int, int], classes: int):
        super().__init__()
        c0, c1, c2 = channels
        self.stage0 = nn.Sequential(_block(dims, c0), _block(c0, c0))
        self.up1 = nn.Sequential(
            nn.ConvTranspose3d(c0, c1, 2, 2, bias=False), nn.BatchNorm3d(c1), nn.ReLU(inplace=True), _block(c1, c1)
        )
        self.up2 = nn.ConvTranspose3d(c1, c2, 2, 2)
        self.point2 = nn.Conv3d(c2, c2, 1)
        self.classify = nn.ModuleList(nn.Conv3d(c, classes, 1) for c in channels)
        self.path = InferencePath()  # set by Co3SOP.use
        # each ACTIVATIONS' calibrated range (0: none), loaded from a checkpoint's int8 entry (`Co3SOP.calibrate`)
        self.register_buffer("int8_ranges", torch.zeros(len(self.ACTIVATIONS)), persistent=False)
        self._int8: tuple | None = None  # (the int8 layers, each activation's step), made by `quantize`

    @property
    def calibrated(self) -> bool:
        return bool((self.int8_ranges > 0).all())

    def quantize(self) -> bool:
        """Make the int8 layers from the weights and ranges as they are now (or none, where the head has no
        calibration or the machine cannot run them); whether there are some."""
        self._int8 = None
        c1, c2, k = self.up2.in_channels, self.up2.out_channels, self.classify[2].out_channels
        if self.calibrated and quantized.onednn_int8() and octant_kernel.available(c1, c2, k, "int8"):
            s = self._step_sizes()
            (first, w0, b0), (second, w1, b1), (_, w2, b2), (block, w3, b3) = self.int8_layers()
            # rows (dz, dx, dy, C1) as in `parents`: a coarse voxel's 8 octants, z-outer
            up = w2.permute(0, 4, 2, 3, 1).flatten(1)  # (C0, 8*C1)
            layers = (
                quantized.Int8ConvReLU(first, w0, b0, s[0], s[1], in_zero=128),
                quantized.Int8ConvReLU(second, w1, b1, s[1], s[2]),
                quantized.Int8LinearReLU(up.t(), b2.repeat(8), s[2], s[3]),
                quantized.Int8ConvReLU(block, w3, b3, s[3], s[4]),
            )
            self._int8 = (layers, s)
        return self._int8 is not None

    def folded_int8_layers(self) -> list[tuple[nn.Module, torch.Tensor, torch.Tensor]]:
        """Each of INT8_LAYERS: its layer and the float layer's weights and bias (Cout,) with its batch norm folded
        in; the transposed convolution's (C0, C1, 2, 2, 2)."""
        conv, norm = self.up1[0], self.up1[1]
        scale, shift = folded_norm(norm, conv.bias)  # (C1,)
        up = (conv.weight * scale[:, None, None, None]).detach().float(), shift.detach().float()
        return [
            (self.stage0[0][0], *quantized.folded_conv(self.stage0[0][0], self.stage0[0][1])),
            (self.stage0[1][0], *quantized.folded_conv(self.stage0[1][0], self.stage0[1][1])),
            (conv, *up),
            (self.up1[3][0], *quantized.folded_conv(self.up1[3][0], self.up1[3][1])),
        ]

    def int8_emulated(self, x, layers: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
        """The int8 path's layers up to 1/2 emulated in float32 on folded (weight, bias) of each of INT8_LAYERS:
        weights and activations rounded to its int8 and uint8 steps, straight through for the gradients: x
        (B, C, X/4, Y/4, Z/4) -> the 1/2 features (B, C1, X/2, Y/2, Z/2) the last stage reads. What
        quantization-aware fine-tuning trains `layers` through."""
        s = self._step_sizes()
        first, second, up, block = self.stage0[0][0], self.stage0[1][0], self.up1[0], self.up1[3][0]

        def conv(m, i, f):
            weight, bias = layers[i]
            return F.relu(F.conv3d(f, quantized.fake_int8_weight(weight), bias, m.stride, m.padding, m.dilation))

        f = quantized.fake_quantized(x.float(), s[0], zero=128)
        f = quantized.fake_quantized(conv(first, 0, f), s[1])
        f = quantized.fake_quantized(conv(second, 1, f), s[2])
        weight, bias = layers[2]  # (C0, C1, 2, 2, 2): int8 per output row, a (C1, octant) pair, as `quantize` has it
        rows = quantized.fake_int8_weight(weight.permute(1, 2, 3, 4, 0).flatten(0, 3))  # (C1*8, C0)
        weight = rows.view(*weight.shape[1:], weight.shape[0]).permute(4, 0, 1, 2, 3)
        f = quantized.fake_quantized(F.relu(F.conv_transpose3d(f, weight, bias, up.stride)), s[3])
        return quantized.fake_quantized(conv(block, 3, f), s[4])

    def _step_sizes(self) -> list[float]:
        """Each of ACTIVATIONS' quantization step: its calibrated range / its STEPS."""
        if not self.calibrated:
            raise ValueError("the int8 path needs a calibration: this head has none")
        return [r / n for r, n in zip(self.int8_ranges.tolist(), self.STEPS)]

    def full(self, f1) -> torch.Tensor:
        """The 1/2 features (B, C1, X/2, Y/2, Z/2) -> the full-resolution logits (B, K, X, Y, Z)."""
        return self.classify[2](F.relu(self.point2(F.relu(self.up2(f1)))))

    def octant_logits(self, f1, parents: torch.Tensor) -> torch.Tensor:
        """`full`'s logits of the 8 octants of chosen voxels at 1/2: f1 (B, C1, X/2, Y/2, Z/2), parents (B, N) flat
        indices into it -> (B, 8, K, N), octants in the transposed convolution's kernel order."""
        h = self._octants(f1, parents) + self.up2.bias[:, None]  # (B, 8, C2, N)
        h = F.relu(
            torch.einsum("bocn,dc->bodn", F.relu(h), self.point2.weight[:, :, 0, 0, 0]) + self.point2.bias[:, None]
        )
        cls = self.classify[2]
        return torch.einsum("bocn,kc->bokn", h, cls.weight[:, :, 0, 0, 0]) + cls.bias[:, None]

    def _octants(self, f1, parents: torch.Tensor) -> torch.Tensor:
        """The transposed convolution to full resolution, before its bias, at the 8 octants of chosen voxels at 1/2:
        f1 (B, C1, X/2, Y/2, Z/2), parents (B, N) flat indices into it -> (B, 8, C2, N)."""
        b, c1 = f1.shape[:2]
        feat = torch.gather(f1.flatten(2), 2, parents[:, None].expand(b, c1, -1))  # (B, C1, N)
        return torch.einsum("bcn,cdo->bodn", feat, self.up2.weight.flatten(2))

    @torch.no_grad()
    def activations(self, x) -> list[torch.Tensor]:
        """The float32 forward's ACTIVATIONS for x (B, C, X/4, Y/4, Z/4), as the int8 path quantizes them (the input
        by its magnitude): what a calibration measures."""
        f0 = self.stage0[0](x)
        f1 = self.stage0[1](f0)
        u = self.up1[2](self.up1[1](self.up1[0](f1)))
        return [x.abs(), f0, f1, u, self.up1[3](u)]

    def _parents_int8(self, x) -> tuple[torch.Tensor, float]:
        """x (B, C, X/4, Y/4, Z/4) -> the 1/2 features on the int8 layers: (B, X/2, Y/2, Z/2, C1) uint8, channels
        innermost in memory (z outermost), and their scale."""
        (first, second, up, block), s = self._int8
        b, _, x0, y0, z0 = x.shape
        if quantize_kernel.fits(x):  # the fusion's output: channels-last
            q = quantize_kernel.quantized_z_outer(x, 1 / s[0], 128, torch.get_num_threads())  # (B, Z, X, Y, C)
        else:
            q = (x.permute(0, 4, 2, 3, 1) * (1 / s[0])).add_(128).round_().clamp_(0, 255).to(torch.uint8).contiguous()
        f = second(first(quantized.Int8Volume(q.permute(0, 4, 1, 2, 3), s[0])))  # (B, C0, Z, X, Y) views
        rows = f.values.permute(0, 2, 3, 4, 1).reshape(-1, f.values.shape[1])  # (B*Z*X*Y, C0): no copy
        c1 = block.bias.shape[0]
        u = up(rows, s[2]).view(b, z0, x0, y0, 2, 2, 2, c1).permute(0, 1, 4, 2, 5, 3, 6, 7)  # (B, Z0, dz, X0, ...)
        u = u.reshape(b, 2 * z0, 2 * x0, 2 * y0, c1).permute(0, 4, 1, 2, 3)  # (B, C1, Z1, X1, Y1) views
        f1 = block(quantized.Int8Volume(u, s[3]))
        return f1.values.permute(0, 3, 4, 2, 1), s[4]  # (B, X1, Y1, Z1, C1): no copy

    def coarse(self, x):
        """x: (B, C, X/4, Y/4, Z/4) -> features at 1/4 and 1/2."""
        f0 = self.stage0(x)
        return f0, self.up1(f0)

    def parents(self, x):
        """x: (B, C, X/4, Y/4, Z/4) -> the 1/2 features as (B, X/2, Y/2, Z/2, C1) with channels innermost in memory:
        `coarse`'s f1, channels last. The stride-2 transposed convolution is one matrix product per coarse voxel whose
        8 octants land in place, and the 3x3x3 block reads and writes channels-last, so no layout copy is left.
        On a reduced-precision path the volumes are z-outer (conv_norm.py: oneDNN's convolutions run faster on
        them), the batch norm is folded into that product and the ReLU applied in place, in the path's
        precision: at 1/2 every pass over the volume is memory traffic, and this saves three of them."""
        reduced = self.path.reduced
        f0 = self.stage0(z_outer(x) if reduced else x)  # (B, C0, X0, Y0, Z0)
        conv, norm, block = self.up1[0], self.up1[1], self.up1[3]
        b, c0, x0, y0, z0 = f0.shape
        c1 = conv.out_channels
        if reduced:
            rows = f0.permute(0, 4, 2, 3, 1).reshape(b * z0 * x0 * y0, c0)  # (B*P0, C0) in (z, x, y) order: no copy
            scale, shift = folded_norm(norm, conv.bias)  # (C1,), (C1,)
            # columns (dz, dx, dy, C1): a parent's two octants along y, innermost in the z-outer volume, land in
            # place as one run of 2*C1 values (a cache line at C1 = 16) rather than two runs of C1
            weight = (conv.weight * scale[:, None, None, None]).permute(0, 4, 2, 3, 1).flatten(1)  # (C0, 8*C1)
            u = self.path.linear(rows, weight.t(), shift.repeat(8), relu=True)  # (B*P0, 8*C1)
            u = u.view(b, z0, x0, y0, 2, 2, 2, c1).permute(0, 1, 4, 2, 5, 3, 6, 7)  # (B, Z0, dz, X0, dx, Y0, dy, C1)
            u = u.reshape(b, 2 * z0, 2 * x0, 2 * y0, c1).permute(0, 4, 2, 3, 1)  # (B, C1, X/2, Y/2, Z/2), z-outer
            f1 = block(u)
        else:
            rows = f0.flatten(2).transpose(1, 2)  # (B, P0, C0)
            u = rows @ conv.weight.flatten(1)  # (B, P0, C1*8): kernel offsets (i, j, k) last
            if conv.bias is not None:
                u = u + conv.bias.repeat_interleave(8)
            u = u.view(b, x0, y0, z0, c1, 2, 2, 2).permute(0, 1, 5, 2, 6, 3, 7, 4)
            u = u.reshape(b, 2 * x0, 2 * y0, 2 * z0, c1).permute(0, 4, 1, 2, 3)  # (B, C1, X/2, Y/2, Z/2), channels-last
            f1 = block(F.relu(norm(u)))
        return f1.permute(0, 2, 3, 4, 1)  # (B, X/2, Y/2, Z/2, C1): no copy

    def forward(self, x):
        f0, f1 = self.coarse(x)
        return [self.classify[0](f0), self.classify[1](f1), self.full(f1)]  # logits (B, K, X/s, Y/s, Z/s), s = 4, 2, 1

    @torch.no_grad()
    def labels(self, x, chunk: int = 8192, compiled: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (B, C, X/4, Y/4, Z/4) -> full-resolution labels and round(255 * p(label)), both (B, X, Y, Z) uint8.

        Per chunk of parent voxels at 1/2: the 8 octants' features (the transposed convolution's 8 kernel
        slices), the pointwise layers, the classifier, then argmax and the label's softmax probability.
        compiled: the compiled kernel (default: as the model's inference path says, where it compiles) or the
        PyTorch loop. The 1/2 features follow the path's precision; the last stage sums in float32, its products
        in bfloat16 on a bfloat16 path where the CPU computes them (`octant_kernel.dot_bf16`). On an int8 path with
        the int8 layers made (`quantize`), the 1/2 features come from them, uint8, and the kernel reads them so.
        """
        if self.path.int8 and self._int8 is not None and self.path.kernels(x) and compiled is not False:
            parents, scale = self._parents_int8(x)  # (B, X1, Y1, Z1, C1) uint8
            threads = torch.get_num_threads()
            pairs = [
                octant_kernel.octant_labels(p, self.up2, self.point2, self.classify[2], threads, "int8", scale)
                for p in parents
            ]
            return _batched(pairs)
        with self.path.autocast():
            parents = self.parents(x)  # (B, X1, Y1, Z1, C1)
        b, x1, y1, z1 = parents.shape[:4]
        c1, c2 = self.up2.in_channels, self.up2.out_channels
        precision = self.path.floats
        if compiled is None:
            compiled = self.path.kernels(x) and octant_kernel.available(
                c1, c2, self.classify[2].out_channels, precision
            )
        if compiled:
            pairs = [
                octant_kernel.octant_labels(
                    p, self.up2, self.point2, self.classify[2], torch.get_num_threads(), precision
                )
                for p in parents
            ]
            return _batched(pairs)
        parents = parents.float().reshape(b, -1, c1)  # (B, P, C1), flat (x, y, z) order
        up_w = self.up2.weight.flatten(2).permute(0, 2, 1).reshape(c1, 8 * c2)  # (C1, 8*C2): octant-major
        up_b = self.up2.bias.repeat(8)  # (8*C2,)
        point_w, point_b = self.point2.weight[:, :, 0, 0, 0].t(), self.point2.bias  # (C2, C2), (C2,)
        cls_w, cls_b = self.classify[2].weight[:, :, 0, 0, 0].t(), self.classify[2].bias  # (C2, K), (K,)
        n = parents.shape[1]
        labels = torch.empty(b, n, 8, dtype=torch.uint8, device=x.device)
        confidence = torch.empty(b, n, 8, dtype=torch.uint8, device=x.device)
        for start in range(0, n, chunk):
            h = F.relu(parents[:, start : start + chunk] @ up_w + up_b)  # (B, n, 8*C2)
            h = F.relu(h.unflatten(-1, (8, c2)) @ point_w + point_b)  # (B, n, 8, C2)
            logits = h @ cls_w + cls_b  # (B, n, 8, K)
            top, label = logits.max(-1)  # (B, n, 8)
            prob = 1.0 / torch.exp(logits - top[..., None]).sum(-1)  # softmax at the label
            labels[:, start : start + chunk] = label.to(torch.uint8)
            confidence[:, start : start + chunk] = torch.round(prob * 255).to(torch.uint8)

        def fine(t):  # (B, P, 8) octants of parents -> (B, X, Y, Z)
            return t.view(b, x1, y1, z1, 2, 2, 2).permute(0, 1, 4, 2, 5, 3, 6).reshape(b, 2 * x1, 2 * y1, 2 * z1)

        return fine(labels), fine(confidence)

    def forward_at(self, x, index: torch.Tensor):
        """Logits at 1/4 and 1/2 (dense) and at full resolution for flat voxel indices (B, N) -> (B, K, N)."""
        f0, f1 = self.coarse(x)
        b, _, x1, y1, z1 = f1.shape
        fy, fz = 2 * y1, 2 * z1
        i, j, k = index // (fy * fz), (index // fz) % fy, index % fz
        parent = ((i // 2) * y1 + j // 2) * z1 + k // 2  # (B, N) flat index at 1/2
        # all 8 octants of the parent, then the voxel's own: gathering a kernel slice per voxel instead
        # makes the backward pass scatter N kernel slices into the kernel one by one
        c2 = self.up2.out_channels
        octants = self._octants(f1, parent)  # (B, 8, C2, N)
        octant = ((i % 2) * 4 + (j % 2) * 2 + k % 2)[:, None, None].expand(b, 1, c2, -1)  # (B, 1, C2, N)
        f2 = torch.gather(octants, 1, octant)[:, 0] + self.up2.bias[None, :, None]  # (B, C2, N)
        f2 = F.relu(
            torch.einsum("bcn,dc->bdn", F.relu(f2), self.point2.weight[:, :, 0, 0, 0]) + self.point2.bias[None, :, None]
        )
        cls = self.classify[2]
        return [
            self.classify[0](f0),
            self.classify[1](f1),
            torch.einsum("bcn,kc->bkn", f2, cls.weight[:, :, 0, 0, 0]) + cls.bias[None, :, None],
        ]
