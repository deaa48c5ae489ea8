"""Confidence-masked voxel fusion: the ego's voxels attend to the warped collaborators' voxels.

Hybrid mask (Co3SOP-Base): a collaborator's voxel counts where the warp filled
it (warp mask) and its confidence beats the ego's (confidence mask). Only ego
voxels that at least one collaborator may inform are queried, so the
attention is computed only where the mask selects; every other voxel keeps the
ego's own feature. `dense=True` computes every voxel and keeps the same ones:
the reference the masked path is tested against.
"""

from __future__ import annotations

import torch
from torch import nn

from co3sop_nodes.kernels.transpose import transposed
from co3sop_nodes.model.config import AttentionConfig
from co3sop_nodes.model.deform_attn import DeformableAttention3d
from co3sop_nodes.model.path import InferencePath
from co3sop_nodes.model.positional import sine_encoding_3d
from co3sop_nodes.model.post_norm import AddNorm, FeedForward


def hybrid_mask(ego_conf, warped_conf, warp_mask):
    """(B, 1, X, Y, Z), (B, A, X, Y, Z), (B, A, X, Y, Z) bool -> (B, A, X, Y, Z) bool."""
    return warp_mask & (warped_conf > ego_conf)


def channels_last_rows(volume: torch.Tensor) -> torch.Tensor:
    """(B, C, X, Y, Z) -> a contiguous (B, V, C) copy, each voxel's channels together: one 2D transposition per
    sample (compiled, where PyTorch copies a transposed view element by element)."""
    b, c = volume.shape[:2]
    out = volume.new_empty(b, volume[0].numel() // c, c)
    for i in range(b):
        transposed(volume[i].reshape(c, -1), torch.get_num_threads(), out[i])
    return out


class FusionLayer(nn.Module):
    def __init__(self, dims: int, att: AttentionConfig, slots: int, extent_voxels):
        super().__init__()
        self.attention = DeformableAttention3d(dims, att.heads, att.points, slots, extent_voxels)
        self.norm1, self.norm2 = AddNorm(dims), AddNorm(dims)
        self.ffn = FeedForward(dims, 2 * dims)

    def forward(self, query, pos, reference, values, mask):
        x = self.norm1(query, self.attention(query + pos, reference, values, mask))
        return self.norm2(x, self.ffn(x))


class VoxelFusion(nn.Module):
    def __init__(self, dims: int, att: AttentionConfig, slots: int, dims_xyz: tuple[int, int, int]):
        super().__init__()
        self.layers = nn.ModuleList(FusionLayer(dims, att, slots, dims_xyz) for _ in range(att.layers))
        x, y, z = dims_xyz
        axes = [(torch.arange(n, dtype=torch.float32) + 0.5) / n for n in (x, y, z)]
        centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # (V, 3) in [0, 1]
        self.register_buffer("reference", centres, persistent=False)
        self.register_buffer("pos", sine_encoding_3d(centres, dims), persistent=False)
        self.path = InferencePath()  # set by Co3SOP.use

    def forward(self, ego, values, mask, dense: bool = False):
        """ego: (B, C, X, Y, Z); values: (B, A, C, X, Y, Z) warped; mask: (B, A, X, Y, Z) -> fused (B, C, X, Y, Z)."""
        b, c = ego.shape[:2]
        flat = ego.flatten(2).transpose(1, 2)  # (B, V, C)
        per_voxel = mask.flatten(2).transpose(1, 2)  # (B, V, A)
        selected = per_voxel.any(-1)  # (B, V)
        # float32 keeps the ego's layout; a reduced path writes whole voxels into a channels-last copy, which its
        # channels-last convolutions take as it is (in the ego's layout each voxel's channels lie V apart)
        out = channels_last_rows(ego) if self.path.reduced else flat.clone()
        for i in range(b):
            idx = torch.arange(flat.shape[1], device=ego.device) if dense else selected[i].nonzero()[:, 0]
            n, rows = len(idx), self.path.query_rows
            if not n:
                continue
            if not dense and self.path.kernels(ego) and n % rows:
                # repeats of the last query, whose results are dropped: each query's is computed on its own
                idx = torch.cat([idx, idx[-1:].expand(rows - n % rows)])
            # the queries from the copy: on a reduced path whole channels-last rows, where the ego's layout has a
            # voxel's channels V apart; index_select gathers rows several times faster than indexing with a tensor
            q, m = out[i].index_select(0, idx)[None], per_voxel[i, idx][None]  # (1, Q, C), (1, Q, A)
            pos, reference = self.pos.index_select(0, idx)[None], self.reference.index_select(0, idx)[None]
            for layer in self.layers:
                q = layer(q, pos, reference, values[i : i + 1], m)
            if dense:  # the selected voxels' results only
                keep = selected[i]
                idx, q = idx[keep], q[:, keep]
            else:
                idx, q = idx[:n], q[:, :n]
            out[i].index_copy_(0, idx, q[0].to(out.dtype))
        return out.transpose(1, 2).reshape(ego.shape)  # a view: channels-last in memory on a reduced path
