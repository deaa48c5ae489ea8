"""Image-to-voxel lifting: SurroundOcc-style deformable cross-attention from learnable voxel queries.

Each voxel query's 3D reference point (its centre in the LiDAR frame) is
projected into every camera with lidar2img; only cameras that see it (in front
of the camera, inside the image) attend, sampling every FPN level around the
projected point with learned offsets; the result is averaged over those cameras.
"""

from __future__ import annotations

import torch
from torch import nn

from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.kernels import deform as deform_kernel
from co3sop_nodes.model.deform_attn import sample_2d
from co3sop_nodes.model.path import InferencePath
from co3sop_nodes.model.post_norm import AddNorm, FeedForward


def voxel_centres(grid: GridSpec) -> torch.Tensor:
    """(X*Y*Z, 3) voxel centres in metres, flat order x-major (as GridSpec)."""
    axes = [
        grid.origin[a] + (torch.arange(n, dtype=torch.float32) + 0.5) * grid.voxel_size for a, n in enumerate(grid.dims)
    ]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)


def project(points: torch.Tensor, lidar2img: torch.Tensor, image_size: tuple[int, int]):
    """points (Q, 3) LiDAR frame; lidar2img (B, N, 4, 4) -> uv in [0, 1] (B, N, Q, 2), visible (B, N, Q).

    In float32 whatever the autocast around it: in bfloat16 a projected point would move by up to a pixel and
    the visibility at an image's edges with it."""
    with torch.autocast(points.device.type, enabled=False):
        homo = torch.cat([points.float(), torch.ones_like(points[:, :1], dtype=torch.float32)], dim=-1)  # (Q, 4)
        cam = torch.einsum("bnij,qj->bnqi", lidar2img.float(), homo)  # (B, N, Q, 4): (u*d, v*d, d, 1)
        depth = cam[..., 2]
        uv = cam[..., :2] / depth.clamp(min=1e-5)[..., None]
        uv = uv / torch.tensor(image_size, dtype=uv.dtype, device=uv.device)
        # the extremes of (u, v), not all() of each comparison: fewer passes over the pairs (a NaN fails either way)
        visible = (depth > 1e-5) & (uv.amin(-1) >= 0) & (uv.amax(-1) <= 1)
    return uv, visible


class ImageCrossAttention(nn.Module):
    def __init__(self, dims: int, heads: int, levels: int, points: int):
        super().__init__()
        self.heads, self.levels, self.points = heads, levels, points
        self.offsets = nn.Linear(dims, heads * levels * points * 2)
        self.weights = nn.Linear(dims, heads * levels * points)
        self.value = nn.Linear(dims, dims)
        self.output = nn.Linear(dims, dims)
        self.path = InferencePath()  # set by Co3SOP.use
        nn.init.zeros_(self.offsets.weight)
        with torch.no_grad():  # initial offsets on a small ring around the reference point
            angle = torch.arange(heads * points, dtype=torch.float32) * (2 * torch.pi / (heads * points))
            ring = torch.stack([angle.cos(), angle.sin()], -1).view(heads, 1, points, 2) * 2.0
            self.offsets.bias.copy_(ring.expand(heads, levels, points, 2).reshape(-1))

    def projections(self, query):
        """query (B, Q, C) -> the sampling offsets (B, Q, H, L, P, 2) in pixels of each level and the attention
        weights' logits (B, Q, H, L*P)."""
        b, q, _ = query.shape
        h, lv, p = self.heads, self.levels, self.points
        return self.offsets(query).view(b, q, h, lv, p, 2), self.weights(query).view(b, q, h, lv * p)

    def forward(self, query, uv, visible, feats, projected=None):
        """query: (B, Q, C); uv: (B, N, Q, 2); visible: (B, N, Q); feats: L x (B*N, C, Hl, Wl); projected: the
        query's `projections` where the caller has them. -> (B, Q, C)."""
        b, q, c = query.shape
        n = uv.shape[1]
        h, lv, p = self.heads, self.levels, self.points
        offsets, logits = self.projections(query) if projected is None else projected
        values = [self.value(f.permute(0, 2, 3, 1)) for f in feats]  # L x (B*N, Hl, Wl, C)
        # inference on the CPU: the compiled sampler, from the channels-last maps (tested equal to the path below)
        if self.path.kernels(query) and deform_kernel.available(c // h, lv * p):
            pooled = [
                deform_kernel.sample_cameras(
                    [v[i * n : (i + 1) * n] for v in values],
                    uv[i],
                    visible[i],
                    offsets[i],
                    logits[i],
                    torch.get_num_threads(),
                )
                for i in range(b)
            ]
            return self.output(torch.stack(pooled))
        # in float32 whatever the path's precision: the CPU's softmax over bfloat16 takes three times as long
        w = torch.softmax(logits.float(), -1).view(b, q, h, lv, p)
        shapes = torch.tensor(
            [[f.shape[-1], f.shape[-2]] for f in feats], dtype=query.dtype, device=query.device
        )  # (L, 2) W, H
        off = offsets / shapes[None, None, None, :, None, :]  # pixels -> [0, 1]
        # per level, every image's value map split by head: L x (B*N) x (H, C/H, Hl, Wl)
        values = [v.permute(0, 3, 1, 2).unflatten(1, (h, c // h)).unbind(0) for v in values]
        pooled = []
        for i in range(b):
            # only the (camera, query) pairs where the camera sees the query, camera-major
            cam, idx = visible[i].nonzero(as_tuple=True)
            # one gather for all pairs (a gather per camera would zero-fill a full-size gradient for each), then
            # split by camera
            per_cam = torch.bincount(cam, minlength=n).tolist()
            locs = (uv[i, cam, idx][:, None, None, None, :] + off[i, idx]).split(per_cam)  # N x (Qv, H, L, P, 2)
            weights = w[i, idx].split(per_cam)  # N x (Qv, H, L, P)
            sampled = [
                sample_2d([v[i * n + k] for v in values], locs[k][None], weights[k][None])[0]
                for k in range(n)
                if per_cam[k]
            ]
            total = query.new_zeros(q, c)
            if sampled:
                total = total.index_add(0, idx, torch.cat(sampled))  # (Q, C)
            count = torch.bincount(idx, minlength=q).clamp(min=1).to(query.dtype)[:, None]
            pooled.append(total / count)  # mean over the cameras that see each query
        return self.output(torch.stack(pooled))


class LiftingLayer(nn.Module):
    """Cross-attention + FFN with residuals and layer norms (post-norm, as BEVFormer/SurroundOcc)."""

    def __init__(self, dims: int, heads: int, levels: int, points: int):
        super().__init__()
        self.attention = ImageCrossAttention(dims, heads, levels, points)
        self.norm1, self.norm2 = AddNorm(dims), AddNorm(dims)
        self.ffn = FeedForward(dims, 2 * dims)

    def forward(self, query, uv, visible, feats, projected=None):
        """As ImageCrossAttention.forward."""
        query = self.norm1(query, self.attention(query, uv, visible, feats, projected))
        return self.norm2(query, self.ffn(query))
