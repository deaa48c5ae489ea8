"""3D affine warp of a neighbour's voxel volume into the ego's frame (affine_grid + 5D grid_sample).

Both volumes share one GridSpec, each in its own agent's LiDAR frame. For an
ego voxel centre p_e, the neighbour's grid is read at p_n = T_n<-e p_e. In the
normalised coordinates u of grid_sample (u = D^-1 (p - c), c the grid centre,
D its half extents), that is u_n = (D^-1 R D) u_e + D^-1 (R c + t - c) with
[R | t] = T_n<-e, an affine map `affine_grid` builds. grid_sample orders a 5D
volume's axes (D, H, W) = (X, Y, Z) but its coordinates (W, H, D) = (z, y, x):
the matrix is conjugated by that axis reversal. At inference on the CPU the
resampling runs as a compiled kernel on channels-last volumes (`warp_compiled`,
tested equal to `warp_with_mask`).
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np
import torch
import torch.nn.functional as F

from co3sop_nodes import kernels
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.kernels.transpose import transposed

MAX_FEATURES = 256  # as warp.c's

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


def warp(
    volume: torch.Tensor, neighbour_from_ego: torch.Tensor, grid: GridSpec, mode: str = "bilinear"
) -> torch.Tensor:
    """volume: (B, C, X, Y, Z) in the neighbour's frame -> (B, C, X, Y, Z) resampled on the ego's grid (zeros outside)."""
    theta = warp_theta(neighbour_from_ego, grid).to(volume.device)
    sampling = F.affine_grid(theta, list(volume.shape), align_corners=False)
    return F.grid_sample(volume, sampling, mode=mode, padding_mode="zeros", align_corners=False)


def warp_with_mask(volume: torch.Tensor, neighbour_from_ego: torch.Tensor, grid: GridSpec):
    """The warped volume and the warp mask (B, 1, X, Y, Z): ego voxels the neighbour's grid covers."""
    ones = torch.ones_like(volume[:, :1])
    out = warp(torch.cat([volume, ones], dim=1), neighbour_from_ego, grid)
    return out[:, :-1], out[:, -1:] > 0.5


@cache
def _base_grid(*dims: int) -> np.ndarray:
    """affine_grid's voxel centres along each axis (align_corners=False), computed as it computes them: x's, y's,
    then z's, concatenated."""
    return np.concatenate([(torch.linspace(-1, 1, n) * (n - 1) / n).numpy() for n in dims]).astype(np.float32)


@cache
def _kernel(bfloat16: bool = False):
    """The warp writing its features in float32, or with `bfloat16` rounded to bfloat16."""
    lib = kernels.load("warp")
    if lib is None:
        return None
    fn = lib.warp_trilinear_bf16 if bfloat16 else lib.warp_trilinear
    fn.argtypes, fn.restype = (
        [*[ctypes.c_void_p] * 2, *[ctypes.c_int64] * 4, *[ctypes.c_void_p] * 5, ctypes.c_int64, ctypes.c_int64],
        None,
    )
    return fn


def compiled_available() -> bool:
    """Whether the compiled warp compiles here (compiling it on first call; CO3SOP_NATIVE=0: never)."""
    return kernels.ENABLED and _kernel() is not None


def warp_compiled(
    features: torch.Tensor,
    confidence: torch.Tensor,
    neighbour_from_ego: torch.Tensor,
    grid: GridSpec,
    threads: int,
    out: tuple[torch.Tensor, torch.Tensor] | None = None,
):
    """`warp_with_mask` of one CPU volume's features (1, C, X, Y, Z) and confidence (1, 1, X, Y, Z), channels-last
    out: warped features (X, Y, Z, C), confidence (X, Y, Z) and warp mask (X, Y, Z). `out`: contiguous tensors of
    those shapes to write the features and confidence into (a fusion's stack of neighbours), fresh float32 ones
    otherwise; features in float32, or bfloat16 (the float32 warp rounded to nearest even, as `.bfloat16()` rounds
    it), the confidence in float32."""
    _, c, nx, ny, nz = features.shape
    if c > MAX_FEATURES:
        raise ValueError(f"warp_compiled: {c} channels, above the kernel's {MAX_FEATURES}")
    theta = kernels.array(warp_theta(neighbour_from_ego, grid)[0])  # (3, 4): the kernel applies affine_grid's map
    base = _base_grid(nx, ny, nz)
    src = kernels.array(transposed(features[0].reshape(c, -1), threads))  # (X*Y*Z, C): channels-last
    conf_src = kernels.array(confidence.reshape(-1))  # (X*Y*Z,)
    warped, conf = out if out is not None else (torch.empty(nx, ny, nz, c), torch.empty(nx, ny, nz))
    if warped.dtype not in (torch.float32, torch.bfloat16) or conf.dtype != torch.float32:
        raise ValueError(f"warp_compiled: writes float32 or bfloat16 features, not {warped.dtype}")
    filled = np.empty((nx, ny, nz), np.float32)
    fn = _kernel(warped.dtype == torch.bfloat16)
    kernels.parallel(
        fn,
        (
            src.ctypes.data,
            conf_src.ctypes.data,
            nx,
            ny,
            nz,
            c,
            theta.ctypes.data,
            base.ctypes.data,
            warped.data_ptr(),
            conf.data_ptr(),
            filled.ctypes.data,
        ),
        nx * ny * nz,
        threads,
    )
    return warped, conf, torch.from_numpy(filled) > 0.5
