"""Deformable attention in pure PyTorch: multi-scale 2D sampling (image -> voxel) and 3D sampling (agent -> agent).

Sampling locations are normalised to [0, 1] per axis and mapped to
`grid_sample` coordinates as 2 * loc - 1 (align_corners=False: a voxel or
pixel centre i sits at (i + 0.5) / n); samples outside a map read zeros.
Attention weights are a softmax over (levels x points) per head.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from co3sop_nodes.kernels import deform as deform_kernel
from co3sop_nodes.model.path import InferencePath


def sample_2d(values: list[torch.Tensor], locations: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Multi-scale deformable sampling.

    values: L x (B*H, Ch, Hl, Wl); locations: (B, Q, H, L, P, 2) as (x, y) in [0, 1];
    weights: (B, Q, H, L, P). Returns (B, Q, H*Ch).
    """
    b, q, h, _, p, _ = locations.shape
    out = 0
    # unbind, not indexing per level: each index's backward would zero-fill a gradient of the full tensor
    for value, g, w in zip(values, (2 * locations - 1).unbind(3), weights.unbind(3)):
        g = g.permute(0, 2, 1, 3, 4).reshape(b * h, q, p, 2)  # (B*H, Q, P, 2)
        s = F.grid_sample(value, g, mode="bilinear", padding_mode="zeros", align_corners=False)  # (B*H, Ch, Q, P)
        w = w.permute(0, 2, 1, 3).reshape(b * h, 1, q, p)
        out = out + (s * w).sum(-1)  # (B*H, Ch, Q)
    ch = out.shape[1]
    return out.view(b, h, ch, q).permute(0, 3, 1, 2).reshape(b, q, h * ch)


def sample_3d(values: torch.Tensor, locations: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Deformable sampling over agents' voxel volumes.

    values: (B*H, A, Ch, X, Y, Z); locations: (B, Q, H, A, P, 3) as (x, y, z) in [0, 1];
    weights: (B, Q, H, A, P). Returns (B, Q, H*Ch).
    """
    bh, _, ch = values.shape[:3]
    b, q, h, _, p, _ = locations.shape
    # grid_sample reads a 5D input (N, C, D, H, W) = (.., X, Y, Z) with grid coordinates ordered (W, H, D) = (z, y, x)
    grids = (2 * locations - 1).flip(-1)
    out = 0
    for value, g, w in zip(values.unbind(1), grids.unbind(3), weights.unbind(3)):  # per agent
        g = g.permute(0, 2, 1, 3, 4).reshape(bh, q, p, 1, 3)  # (B*H, Q, P, 1, 3)
        s = F.grid_sample(value, g, mode="bilinear", padding_mode="zeros", align_corners=False)  # (B*H, Ch, Q, P, 1)
        w = w.permute(0, 2, 1, 3).reshape(bh, 1, q, p)
        out = out + (s[..., 0] * w).sum(-1)  # (B*H, Ch, Q)
    return out.view(b, h, ch, q).permute(0, 3, 1, 2).reshape(b, q, h * ch)


class DeformableAttention3d(nn.Module):
    """Queries attend to `slots` voxel volumes (the collaborators, nearest first) around their reference points.

    The agents play the role of MSDeformAttn's levels: every (head, agent, point)
    has its own offset and weight; a per-query, per-agent mask removes agents a
    query may not attend to (softmax over the remaining agents x points).
    """

    def __init__(self, dims: int, heads: int, points: int, slots: int, extent_voxels: tuple[int, int, int]):
        super().__init__()
        self.heads, self.points, self.slots = heads, points, slots
        self.offsets = nn.Linear(dims, heads * slots * points * 3)
        self.weights = nn.Linear(dims, heads * slots * points)
        self.value = nn.Linear(dims, dims)
        self.output = nn.Linear(dims, dims)
        self.register_buffer("scale", 1.0 / torch.tensor(extent_voxels, dtype=torch.float32), persistent=False)
        self.path = InferencePath()  # set by Co3SOP.use
        nn.init.zeros_(self.offsets.weight)
        with torch.no_grad():  # initial offsets: points spread along the axes, 1..P voxels away
            direction = torch.tensor(
                [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float32
            )
            init = torch.stack([direction[(i + j) % 6] * (j // 2 + 1) for i in range(heads) for j in range(points)])
            self.offsets.bias.copy_(init.view(heads, 1, points, 3).expand(heads, slots, points, 3).reshape(-1))

    def forward(self, query, reference, values, mask):
        """query: (B, Q, C); reference: (B, Q, 3) in [0, 1]; values: (B, A, C, X, Y, Z); mask: (B, Q, A) bool."""
        b, q, c = query.shape
        a = values.shape[1]
        h, p = self.heads, self.points
        if self.path.kernels(query) and deform_kernel.available(c // h, a * p):
            return self.output(self._sampled(query, reference, values, mask))
        v = self.value(values.permute(0, 1, 3, 4, 5, 2))  # (B, A, X, Y, Z, C)
        offsets = self.offsets(query).view(b, q, h, self.slots, p, 3)  # in voxels
        logits = self.weights(query).view(b, q, h, self.slots, p)[:, :, :, :a]
        logits = logits.masked_fill(~mask[:, :, None, :, None], float("-inf"))
        w = torch.softmax(logits.reshape(b, q, h, a * p), -1).view(b, q, h, a, p)
        w = torch.nan_to_num(w)  # a query with no agent allowed attends to nothing
        v = v.permute(0, 1, 5, 2, 3, 4)  # (B, A, C, X, Y, Z)
        v = v.reshape(b, a, h, c // h, *v.shape[-3:]).transpose(1, 2).reshape(b * h, a, c // h, *v.shape[-3:])
        loc = (
            reference[:, :, None, None, None, :] + offsets[:, :, :, :a] * self.scale
        )  # (B, Q, H, A, P, 3), voxels -> [0, 1]
        return self.output(sample_3d(v, loc, w))  # (B, Q, C)

    def _sampled(self, query, reference, values, mask):
        """Inference on the CPU: the compiled sampler (tested equal to sample_3d), which takes the attention's logits
        and takes their masked softmax itself, from channels-last volumes -> (B, Q, C) before the output projection.
        The projections (offsets and logits for the A agents present only) in the path's precision, as autocast
        would compute them: on a reduced path bfloat16 values, offsets and logits, which the kernel reads as they
        are (the value projection covers every agent's whole volume)."""
        b, q, c = query.shape
        a = values.shape[1]
        h, p = self.heads, self.points
        with torch.autocast(query.device.type, enabled=False):
            x = query.to(self.path.float_dtype)
            offsets = self._present(self.offsets, x, a).view(b, q, h, a, p, 3)  # in voxels
            logits = self._present(self.weights, x, a).view(b, q, h, a, p)
            voxels = values.to(self.path.float_dtype).permute(0, 1, 3, 4, 5, 2)  # (B, A, X, Y, Z, C)
            v = self.path.linear(voxels, self.value.weight, self.value.bias)
        threads = torch.get_num_threads()
        out = [deform_kernel.sample_3d(v[i], reference[i], offsets[i], logits[i], mask[i], threads) for i in range(b)]
        return out[0][None] if b == 1 else torch.stack(out)  # a batch of one (a node's frame): a view, not a copy

    def _present(self, linear: nn.Linear, x: torch.Tensor, a: int) -> torch.Tensor:
        """`linear` (outputs ordered by head, slot, then within a slot) of x (..., C) for the first `a` slots only:
        (..., H a k), k outputs per slot."""
        c = x.shape[-1]
        rows = linear.weight.view(self.heads, self.slots, -1, c)[:, :a].reshape(-1, c)
        return self.path.linear(x, rows, linear.bias.view(self.heads, self.slots, -1)[:, :a].reshape(-1))
