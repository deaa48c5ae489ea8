"""OccFormer's ego-side network: dual-path transformer encoder, top-down neck and mask-classification decoder.

It takes the place of Co3SOP-Base's convolutional head (ModelConfig.head =
"occformer") on the same voxel features (B, C, X, Y, Z) at 1/4 resolution, so
the camera lifting is shared. Facts from OccFormer (Zhang et al., ICCV 2023)
and its code; our own implementation:

- Encoder: stages of dual-path blocks. A block convolves (3x3x3, stride 1 or
  2), then one windowed self-attention block (Swin: pre-norm, relative
  position bias, window 7, shifted on every other block) runs with the same
  weights on every horizontal slice (local path) and on the height-averaged
  BEV plane (global path, followed by a bottleneck ASPP); the two are fused as
  local + sigmoid(1x1x1 conv(local)) x BEV broadcast over height, plus the
  block's shortcut.
- Neck: lateral 1x1x1 convolutions and a top-down path to the decoder width;
  the finest level gives the mask features. (OccFormer's neck adds six
  layers of 3D multi-scale deformable self-attention on the coarse levels;
  here the top-down path alone.)
- Decoder (Mask2Former): learnable queries; each layer is masked cross-
  attention to one encoder level (coarse to fine in turn; the previous
  layer's masks, max-pooled to the level's size so rare classes keep their
  voxels, mask where sigmoid < 0.5), self-attention, FFN, each with a
  residual and post-norm; after every layer, class logits (K + 1, the last is
  "no object") and mask logits = mask embedding . mask features.
- Prediction: score(c) = sum over queries of softmax(class)[c] x sigmoid(mask
  logits upsampled trilinearly to full resolution), argmax over classes.

The training loss (Hungarian matching, class-guided points) is in
`mask_loss.py`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from co3sop_nodes.model.config import ModelConfig, OccFormerConfig
from co3sop_nodes.model.positional import sine_encoding_3d

LEVELS = 3  # the decoder attends to the coarsest three encoder levels, as OccFormer's


def group_norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(math.gcd(32, channels), channels)


class WindowBlock(nn.Module):
    """Swin block on (N, C, H, W): pre-norm windowed multi-head self-attention with a learned relative position
    bias (cyclically shifted by half a window when `shift`), then a GELU FFN of width C; both residual."""

    def __init__(self, dims: int, heads: int, window: int, shift: bool):
        super().__init__()
        self.heads, self.window, self.shift = heads, window, window // 2 if shift else 0
        self.norm1, self.norm2 = nn.LayerNorm(dims), nn.LayerNorm(dims)
        self.qkv, self.proj = nn.Linear(dims, 3 * dims), nn.Linear(dims, dims)
        self.bias = nn.Parameter(torch.randn((2 * window - 1) ** 2, heads) * 0.02)
        ij = torch.stack(torch.meshgrid(torch.arange(window), torch.arange(window), indexing="ij")).flatten(1)  # (2, L)
        rel = ij[:, :, None] - ij[:, None, :] + window - 1  # (2, L, L) in [0, 2w - 2]
        self.register_buffer("bias_index", rel[0] * (2 * window - 1) + rel[1], persistent=False)  # (L, L)
        self.ffn = nn.Sequential(nn.Linear(dims, dims), nn.GELU(), nn.Linear(dims, dims))

    def _windows(self, t: torch.Tensor) -> torch.Tensor:
        """(N, Hp, Wp, C) -> (N, nW, L, C) windows in row-major order."""
        n, hp, wp, c = t.shape
        w = self.window
        return t.view(n, hp // w, w, wp // w, w, c).permute(0, 1, 3, 2, 4, 5).reshape(n, -1, w * w, c)

    def _shift_mask(self, hp: int, wp: int, device) -> torch.Tensor:
        """(nW, L, L) additive mask: after the cyclic shift, a window may join regions that are not neighbours
        (-inf, not Swin's -100: their weights are then exactly zero; a token always sees its own region)."""
        region = torch.zeros(1, hp, wp, 1, device=device)
        w, s = self.window, self.shift
        cuts = (slice(0, -w), slice(-w, -s), slice(-s, None))
        for k, (a, b) in enumerate((a, b) for a in cuts for b in cuts):
            region[:, a, b] = k
        ids = self._windows(region)[0, :, :, 0]  # (nW, L)
        return torch.zeros(ids.shape[0], ids.shape[1], ids.shape[1], device=device).masked_fill(
            ids[:, None, :] != ids[:, :, None], float("-inf")
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, c, h, w = x.shape  # (N, C, H, W)
        t = x.permute(0, 2, 3, 1)  # (N, H, W, C)
        y = F.pad(self.norm1(t), (0, 0, 0, -w % self.window, 0, -h % self.window))  # (N, Hp, Wp, C)
        hp, wp = y.shape[1:3]
        if self.shift:
            y = torch.roll(y, (-self.shift, -self.shift), (1, 2))
        win = self._windows(y)  # (N, nW, L, C)
        nw, length = win.shape[1:3]
        q, k, v = (
            self.qkv(win).view(n, nw, length, 3, self.heads, c // self.heads).permute(3, 0, 1, 4, 2, 5)
        )  # (N, nW, h, L, d)
        attn = (q * (c // self.heads) ** -0.5) @ k.transpose(-1, -2)  # (N, nW, h, L, L)
        attn = attn + self.bias[self.bias_index].permute(2, 0, 1)  # (h, L, L)
        if self.shift:
            attn = attn + self._shift_mask(hp, wp, x.device)[None, :, None]
        out = (attn.softmax(-1) @ v).permute(0, 1, 3, 2, 4).reshape(n, nw, length, c)  # (N, nW, L, C)
        ws = self.window
        out = out.view(n, hp // ws, wp // ws, ws, ws, c).permute(0, 1, 3, 2, 4, 5).reshape(n, hp, wp, c)
        if self.shift:
            out = torch.roll(out, (self.shift, self.shift), (1, 2))
        t = t + self.proj(out[:, :h, :w])
        t = t + self.ffn(self.norm2(t))
        return t.permute(0, 3, 1, 2)


class BottleneckASPP(nn.Module):
    """The global path's context on the BEV plane (N, C, H, W): reduce to C/4, atrous branches (dilations 1, 6,
    12, 18) and image pooling, fuse (with a residual), expand back to C; residual around all of it."""

    def __init__(self, dims: int, dilations: tuple[int, ...] = (1, 6, 12, 18)):
        super().__init__()
        r = max(8, dims // 4)

        def conv(cin, cout, k=1, d=1):
            return nn.Sequential(
                nn.Conv2d(cin, cout, k, padding=d * (k // 2), dilation=d, bias=False),
                group_norm(cout),
                nn.ReLU(inplace=True),
            )

        self.reduce = conv(dims, r)
        self.branches = nn.ModuleList(conv(r, r, 1 if d == 1 else 3, d) for d in dilations)
        self.pool = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(r, r, 1), nn.ReLU(inplace=True))
        self.fuse = nn.Sequential(conv(r * (len(dilations) + 1), r), nn.Dropout(0.1))
        self.expand = conv(r, dims)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.reduce(x)
        parts = [b(y) for b in self.branches] + [self.pool(y).expand_as(y)]
        return x + self.expand(self.fuse(torch.cat(parts, 1)) + y)


class DualPathBlock(nn.Module):
    """(B, Cin, X, Y, Z) -> (B, Cout, X', Y', Z'): convolution, then the local (per slice) and global (BEV) paths
    through one shared window block, fused by a per-voxel weight from the local features."""

    def __init__(self, cin: int, cout: int, stride: int, window: int, shift: bool):
        super().__init__()
        self.conv = nn.Sequential(
            nn.Conv3d(cin, cout, 3, stride, 1, bias=False), group_norm(cout), nn.ReLU(inplace=True)
        )
        self.shortcut = (
            nn.Sequential(nn.Conv3d(cin, cout, 1, stride, bias=False), group_norm(cout))
            if stride > 1 or cin != cout
            else nn.Identity()
        )
        self.window = WindowBlock(cout, max(1, cout // 32), window, shift)
        self.aspp = BottleneckASPP(cout)
        self.weight = nn.Conv3d(cout, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv(x)  # (B, C, X, Y, Z)
        b, c, nx, ny, nz = y.shape
        bev = y.mean(-1)  # (B, C, X, Y): the global path's input
        slices = y.permute(0, 4, 1, 2, 3).reshape(b * nz, c, nx, ny)  # every horizontal slice: the local path
        both = self.window(torch.cat([bev, slices]))  # one set of weights for both paths
        bev, slices = self.aspp(both[:b]), both[b:]
        local = slices.view(b, nz, c, nx, ny).permute(0, 2, 3, 4, 1)  # (B, C, X, Y, Z)
        return local + torch.sigmoid(self.weight(local)) * bev[..., None] + self.shortcut(x)


class DualPathEncoder(nn.Module):
    def __init__(self, dims: int, cfg: OccFormerConfig):
        super().__init__()
        blocks, cin, index = [], dims, 0
        for s, cout in enumerate(cfg.stages):
            stage = []
            for k in range(cfg.blocks):
                stage.append(DualPathBlock(cin, cout, 2 if s > 0 and k == 0 else 1, cfg.window, shift=index % 2 == 1))
                cin, index = cout, index + 1
            blocks.append(nn.Sequential(*stage))
        self.stages = nn.ModuleList(blocks)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, C, X, Y, Z) -> every stage's output, finest first."""
        outs = []
        for stage in self.stages:
            x = stage(x)
            outs.append(x)
        return outs


class TopDownNeck(nn.Module):
    def __init__(self, stages: tuple[int, ...], dims: int):
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv3d(c, dims, 1) for c in stages)
        self.smooth = nn.Sequential(
            nn.Conv3d(dims, dims, 3, padding=1, bias=False), group_norm(dims), nn.ReLU(inplace=True)
        )
        self.mask_features = nn.Conv3d(dims, dims, 1)

    def forward(self, feats: list[torch.Tensor]) -> tuple[list[torch.Tensor], torch.Tensor]:
        """Encoder outputs (finest first) -> the levels coarse to fine (B, D, ...) and mask features (B, D, X, Y, Z)."""
        p = self.lateral[-1](feats[-1])
        levels = [p]
        for lateral, f in zip(reversed(self.lateral[:-1]), reversed(feats[:-1])):
            p = lateral(f) + F.interpolate(p, size=f.shape[2:], mode="trilinear", align_corners=False)
            levels.append(p)
        levels[-1] = self.smooth(levels[-1])
        return levels, self.mask_features(levels[-1])


def _positions(shape: tuple[int, ...], device) -> torch.Tensor:
    """(N, 3) voxel centres of a grid of `shape` in [0, 1], flat (x, y, z) order."""
    axes = [(torch.arange(n, device=device, dtype=torch.float32) + 0.5) / n for n in shape]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


class MaskDecoder(nn.Module):
    def __init__(self, dims: int, queries: int, layers: int, heads: int, levels: int, classes: int):
        super().__init__()
        self.heads = heads
        self.query_feat, self.query_pos = nn.Embedding(queries, dims), nn.Embedding(queries, dims)
        self.level_embed = nn.Embedding(levels, dims)
        self.cross = nn.ModuleList(nn.MultiheadAttention(dims, heads, batch_first=True) for _ in range(layers))
        self.self_attn = nn.ModuleList(nn.MultiheadAttention(dims, heads, batch_first=True) for _ in range(layers))
        self.ffn = nn.ModuleList(
            nn.Sequential(nn.Linear(dims, 8 * dims), nn.ReLU(inplace=True), nn.Linear(8 * dims, dims))
            for _ in range(layers)
        )
        self.norms = nn.ModuleList(nn.ModuleList(nn.LayerNorm(dims) for _ in range(3)) for _ in range(layers))
        self.norm = nn.LayerNorm(dims)
        self.classify = nn.Linear(dims, classes + 1)  # the last: no object
        self.mask_embed = nn.Sequential(
            nn.Linear(dims, dims),
            nn.ReLU(inplace=True),
            nn.Linear(dims, dims),
            nn.ReLU(inplace=True),
            nn.Linear(dims, dims),
        )

    def predict(self, q: torch.Tensor, mask_features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Queries (B, Q, D) -> class logits (B, Q, K+1) and mask logits (B, Q, X, Y, Z) at the mask features' size."""
        h = self.norm(q)
        return self.classify(h), torch.einsum("bqc,bcxyz->bqxyz", self.mask_embed(h), mask_features)

    def _attention_mask(self, masks: torch.Tensor, size: tuple[int, ...]) -> torch.Tensor:
        """(B, Q, X, Y, Z) mask logits -> (B * heads, Q, N) True where a query may not attend (a query whose mask is
        empty attends everywhere)."""
        pooled = F.adaptive_max_pool3d(masks, size) if tuple(masks.shape[2:]) != tuple(size) else masks
        blocked = (pooled.sigmoid() < 0.5).flatten(2)
        blocked = blocked & ~blocked.all(-1, keepdim=True)
        return blocked.repeat_interleave(self.heads, 0).detach()

    def forward(
        self, levels: list[torch.Tensor], mask_features: torch.Tensor
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """levels coarse to fine (B, D, x, y, z), mask features (B, D, X, Y, Z) -> (class logits, mask logits) from
        the initial queries and after every layer."""
        b = mask_features.shape[0]
        memory = [lv.flatten(2).transpose(1, 2) for lv in levels]  # (B, N_l, D)
        pos = [
            sine_encoding_3d(_positions(lv.shape[2:], lv.device), lv.shape[1]) + self.level_embed.weight[i]
            for i, lv in enumerate(levels)
        ]
        q = self.query_feat.weight[None].expand(b, -1, -1)  # (B, Q, D)
        qpos = self.query_pos.weight[None]
        preds = [self.predict(q, mask_features)]
        for i, (cross, self_attn, ffn, (n1, n2, n3)) in enumerate(
            zip(self.cross, self.self_attn, self.ffn, self.norms)
        ):
            lv = i % len(levels)
            blocked = self._attention_mask(preds[-1][1], levels[lv].shape[2:])
            q = n1(q + cross(q + qpos, memory[lv] + pos[lv], memory[lv], attn_mask=blocked, need_weights=False)[0])
            q = n2(q + self_attn(q + qpos, q + qpos, q, need_weights=False)[0])
            q = n3(q + ffn(q))
            preds.append(self.predict(q, mask_features))
        return preds


def masks_at(masks: torch.Tensor, index: torch.Tensor, dims: tuple[int, int, int]) -> torch.Tensor:
    """Mask logits (B, Q, x, y, z) upsampled trilinearly (corners aligned) to the full grid `dims`, at flat voxel
    indices (B, N) -> (B, Q, N); the same values as F.interpolate to `dims` then a gather."""
    nx, ny, nz = dims
    i, j, k = index // (ny * nz), (index // nz) % ny, index % nz

    def norm(v, n):
        return v.float() * (2.0 / max(n - 1, 1)) - 1.0

    grid = torch.stack([norm(k, nz), norm(j, ny), norm(i, nx)], -1)[:, None, None]  # (B, 1, 1, N, 3): (z, y, x)
    return F.grid_sample(masks, grid, mode="bilinear", align_corners=True)[:, :, 0, 0]


def class_scores(logits: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """Class logits (B, Q, K+1) and mask logits (B, Q, ...) -> per-class scores (B, K, ...): sum over queries of
    p(class) x sigmoid(mask)."""
    return torch.einsum("bqk,bq...->bk...", logits.softmax(-1)[..., :-1], masks.sigmoid())


def log_scores(scores: torch.Tensor) -> torch.Tensor:
    """Scores as logits: softmax over classes gives each class's share of the voxel's total score."""
    return scores.clamp_min(1e-12).log()


class OccFormerHead(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        oc = cfg.occformer
        self.dims = cfg.grid.dims
        self.encoder = DualPathEncoder(cfg.embed_dims, oc)
        self.neck = TopDownNeck(oc.stages, oc.dims)
        self.levels = min(LEVELS, len(oc.stages))
        self.decoder = MaskDecoder(oc.dims, oc.queries, oc.layers, oc.heads, self.levels, cfg.num_classes)

    def predict(self, x: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Fused features (B, C, X/4, Y/4, Z/4) -> every decoder output: class logits (B, Q, K+1), mask logits at 1/4."""
        levels, mask_features = self.neck(self.encoder(x))
        return self.decoder(levels[: self.levels], mask_features)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Log-scores at 1/4 and at full resolution (B, K, X, Y, Z): the dense definition `labels` is held to."""
        logits, masks = self.predict(x)[-1]
        b = x.shape[0]
        index = torch.arange(math.prod(self.dims), device=x.device)[None].expand(b, -1)
        fine = class_scores(logits, masks_at(masks, index, self.dims)).view(b, -1, *self.dims)
        return [log_scores(class_scores(logits, masks)), log_scores(fine)]

    @torch.no_grad()
    def labels(
        self, x: torch.Tensor, chunk: int = 65536, compiled: bool | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (B, C, X/4, Y/4, Z/4) -> full-resolution labels and round(255 * the label's share of the scores),
        both (B, X, Y, Z) uint8, a chunk of voxels at a time (`compiled` is accepted for the conv head's
        signature: there is no kernel here)."""
        logits, masks = self.predict(x)[-1]
        b, n = x.shape[0], math.prod(self.dims)
        labels = torch.empty(b, n, dtype=torch.uint8, device=x.device)
        confidence = torch.empty(b, n, dtype=torch.uint8, device=x.device)
        for start in range(0, n, chunk):
            index = torch.arange(start, min(n, start + chunk), device=x.device)[None].expand(b, -1)
            scores = class_scores(logits, masks_at(masks, index, self.dims))  # (B, K, n)
            top, label = scores.max(1)
            labels[:, start : start + chunk] = label.to(torch.uint8)
            share = 1.0 / torch.exp(log_scores(scores) - log_scores(top)[:, None]).sum(
                1
            )  # softmax of the log-scores at the label
            confidence[:, start : start + chunk] = torch.round(share * 255).to(torch.uint8)
        return labels.view(b, *self.dims), confidence.view(b, *self.dims)
