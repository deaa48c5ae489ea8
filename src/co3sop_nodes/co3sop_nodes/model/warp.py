"""3D affine warp of a neighbour's voxel volume into the ego's frame (affine_grid + 5D grid_sample).

Both volumes share one GridSpec, each in its own agent's LiDAR frame. For an
ego voxel centre p_e, the neighbour's grid is read at p_n = T_n<-e p_e. In the
normalised coordinates u of grid_sample (u = D^-1 (p - c), c the grid centre,
D its half extents), that is u_n = (D^-1 R D) u_e + D^-1 (R c + t - c) with
[R | t] = T_n<-e, an affine map `affine_grid` builds. grid_sample orders a 5D
volume's axes (D, H, W) = (X, Y, Z) but its coordinates (W, H, D) = (z, y, x):
the matrix is conjugated by that axis reversal.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..grid import GridSpec

_REVERSE = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])


def warp_theta(neighbour_from_ego: torch.Tensor, grid: GridSpec) -> torch.Tensor:
    """(B, 4, 4) T_n<-e -> (B, 3, 4) affine_grid matrices in grid_sample's (z, y, x) order."""
    t = neighbour_from_ego.to(torch.float64)
    half = torch.tensor(grid.extent, dtype=torch.float64, device=t.device) / 2  # D
    centre = torch.tensor(grid.origin, dtype=torch.float64, device=t.device) + half  # c
    rot, trans = t[:, :3, :3], t[:, :3, 3]
    a = rot * half[None, None, :] / half[None, :, None]  # D^-1 R D
    b = (torch.einsum("bij,j->bi", rot, centre) + trans - centre) / half
    rev = _REVERSE.to(t)
    theta = torch.cat([rev @ a @ rev, (rev @ b[..., None])], dim=-1)
    return theta.to(torch.float32)


def warp(volume: torch.Tensor, neighbour_from_ego: torch.Tensor, grid: GridSpec, mode: str = "bilinear") -> torch.Tensor:
    """volume: (B, C, X, Y, Z) in the neighbour's frame -> (B, C, X, Y, Z) resampled on the ego's grid (zeros outside)."""
    theta = warp_theta(neighbour_from_ego, grid).to(volume.device)
    sampling = F.affine_grid(theta, list(volume.shape), align_corners=False)
    return F.grid_sample(volume, sampling, mode=mode, padding_mode="zeros", align_corners=False)


def warp_with_mask(volume: torch.Tensor, neighbour_from_ego: torch.Tensor, grid: GridSpec):
    """The warped volume and the warp mask (B, 1, X, Y, Z): ego voxels the neighbour's grid covers."""
    ones = torch.ones_like(volume[:, :1])
    out = warp(torch.cat([volume, ones], dim=1), neighbour_from_ego, grid)
    return out[:, :-1], out[:, -1:] > 0.5
