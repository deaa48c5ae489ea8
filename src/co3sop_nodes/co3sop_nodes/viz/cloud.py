"""Occupied voxels as a coloured point list, for PointCloud2 viewers (RViz2, Foxglove) (ROS-free).

Only the voxels a viewer can see: occupied (neither empty nor ignored) with at least one of their six face
neighbours not occupied or outside the grid. A building's inside, most of a scene's occupied voxels, draws
nothing a viewer would see and cost every frame its points (the ego's cloud, the recorder's compression); the
complete grid is the occupancy message itself.
"""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.classes import EMPTY, IGNORE, PALETTE
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.messages.sensors import LABEL_POINTS

# per label value: its packed 0x00RRGGBB colour
_RGB = np.zeros(256, np.uint32)
_RGB[: len(PALETTE)] = (PALETTE[:, 0].astype(np.uint32) << 16) | (PALETTE[:, 1].astype(np.uint32) << 8) | PALETTE[:, 2]
_RGB[len(PALETTE) :] = _RGB[len(PALETTE) - 1]  # out-of-range labels take the last colour (unlabeled)


def occupancy_cloud_reference(labels: np.ndarray, grid: GridSpec) -> np.ndarray:
    """The definition of `occupancy_cloud`: index arrays of the kept voxels, their centres, palette colours."""
    occupied = np.pad((labels != EMPTY) & (labels != IGNORE), 1)  # outside the grid: not occupied
    inner = occupied[1:-1, 1:-1, 1:-1]
    enclosed = inner.copy()
    for axis in range(3):
        for step in (1, -1):
            enclosed &= np.roll(occupied, step, axis)[1:-1, 1:-1, 1:-1]
    idx = np.argwhere(inner & ~enclosed)  # (N, 3) i, j, k
    lab = labels[tuple(idx.T)]
    centres = np.asarray(grid.origin) + (idx + 0.5) * grid.voxel_size
    rgb = PALETTE[np.minimum(lab, len(PALETTE) - 1)].astype(np.uint32)
    cloud = np.zeros(len(idx), LABEL_POINTS)
    cloud["x"], cloud["y"], cloud["z"] = centres.T
    cloud["rgb"] = ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).view(np.float32)
    cloud["label"] = lab
    return cloud


def occupancy_cloud(labels: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(N,) LABEL_POINTS: the centre of every voxel a viewer can see (module docstring), in the grid's frame (C order).

    By comparisons and shifted slices over the grid and one pass over the kept voxels: centres per axis are
    computed once, a voxel's x, y, z are three gathers, not index arrays and fancy indexing over the grid (the same
    bytes as `occupancy_cloud_reference`, tested).
    """
    nx, ny, nz = labels.shape
    shown = (labels != EMPTY) & (labels != IGNORE)  # (X, Y, Z) occupied
    enclosed = shown.copy()  # occupied, and so is every face neighbour (none outside the grid)
    for axis in range(3):
        lo, hi, first, last = ([slice(None)] * 3 for _ in range(4))
        lo[axis], hi[axis], first[axis], last[axis] = slice(None, -1), slice(1, None), 0, -1
        enclosed[tuple(hi)] &= shown[tuple(lo)]
        enclosed[tuple(lo)] &= shown[tuple(hi)]
        enclosed[tuple(first)] = enclosed[tuple(last)] = False
    flat = np.flatnonzero(shown > enclosed)  # (N,) C-order voxel indices of the visible ones
    lab = labels.reshape(-1)[flat]
    ij, k = np.divmod(flat, nz)
    i, j = np.divmod(ij, ny)
    centres = [(np.arange(n, dtype=np.float64) + 0.5) * grid.voxel_size + o for n, o in zip(labels.shape, grid.origin)]
    cloud = np.zeros(len(flat), LABEL_POINTS)  # zeroed padding: the payload is deterministic
    cloud["x"], cloud["y"], cloud["z"] = centres[0][i], centres[1][j], centres[2][k]
    cloud["rgb"] = _RGB[lab].view(np.float32)
    cloud["label"] = lab
    return cloud
