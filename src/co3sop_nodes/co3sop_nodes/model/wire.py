"""A code learned for the V2X wire: each voxel's features and confidence -> K small integers on the sender, and
back on the ego (the halves of one bottleneck, trained with the fusion behind it).

The encoder (the vehicle half's) maps a voxel's C features and its confidence to K values bounded to
[-L, L] (L * tanh) and rounded to integers: int4 on the wire for L <= 7, with no per-message scale, offset or
basis. Rounding passes its gradient straight through while training. The decoder (the ego half's) maps the K
integers of each voxel it received back to C features and a confidence (which the hybrid mask compares with
the ego's own; a voxel not received stays 0 with confidence 0, as any sparse message decodes). A code is named
by its encoder's weights (`code_id`): an ego decodes only messages of the code it was trained with.
"""

from __future__ import annotations

import hashlib

import torch
from torch import nn

from co3sop_nodes.model.config import WireConfig


class WireEncoder(nn.Module):
    def __init__(self, channels: int, cfg: WireConfig):
        super().__init__()
        self.levels = cfg.levels
        self.project = nn.Sequential(
            nn.Linear(channels + 1, 2 * channels), nn.ReLU(inplace=True), nn.Linear(2 * channels, cfg.rank)
        )

    def forward(self, features: torch.Tensor, confidence: torch.Tensor) -> torch.Tensor:
        """(B, C, X, Y, Z), (B, 1, X, Y, Z) -> the code (B, K, X, Y, Z): integers in [-L, L] (while training with
        a gradient, within float rounding of them: rounding's gradient is passed straight through)."""
        x = torch.cat([features, confidence], 1).movedim(1, -1)  # (B, X, Y, Z, C + 1)
        y = self.levels * torch.tanh(self.project(x))  # (B, X, Y, Z, K)
        q = y + (y.round() - y).detach() if torch.is_grad_enabled() else y.round()
        return q.movedim(-1, 1).contiguous()

    def code_id(self) -> str:
        """The code's name: a digest of the encoder's weights, which decide what each integer means."""
        digest = hashlib.sha256()
        for name, tensor in sorted(self.state_dict().items()):
            digest.update(name.encode())
            digest.update(tensor.detach().float().cpu().numpy().tobytes())
        return digest.hexdigest()[:16]


class WireDecoder(nn.Module):
    def __init__(self, channels: int, cfg: WireConfig):
        super().__init__()
        self.channels = channels
        self.expand = nn.Sequential(
            nn.Linear(cfg.rank, 2 * channels), nn.ReLU(inplace=True), nn.Linear(2 * channels, channels + 1)
        )

    def forward(self, code: torch.Tensor, received: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """code (B, K, X, Y, Z), received (B, X, Y, Z) bool -> features (B, C, X, Y, Z) and confidence
        (B, 1, X, Y, Z): decoded where received, 0 elsewhere."""
        b, _, *dims = code.shape
        out = code.new_zeros(b, *dims, self.channels + 1)  # (B, X, Y, Z, C + 1)
        out[received] = self.expand(code.movedim(1, -1)[received])  # only the received voxels: few under a budget
        features = out[..., :-1].movedim(-1, 1)
        confidence = torch.where(received, torch.sigmoid(out[..., -1]), 0.0)[:, None]
        return features.contiguous(), confidence
