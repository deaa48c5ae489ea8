"""Occupied voxels as a coloured point list, for PointCloud2 viewers (RViz2, Foxglove) (ROS-free)."""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.classes import EMPTY, IGNORE, PALETTE
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.messages.sensors import LABEL_POINTS

# per label value: shown as a point (neither empty nor ignored), and its packed 0x00RRGGBB colour
_SHOWN = np.ones(256, bool)
_SHOWN[[EMPTY, IGNORE]] = False
_RGB = np.zeros(256, np.uint32)
_RGB[: len(PALETTE)] = (PALETTE[:, 0].astype(np.uint32) << 16) | (PALETTE[:, 1].astype(np.uint32) << 8) | PALETTE[:, 2]
_RGB[len(PALETTE) :] = _RGB[len(PALETTE) - 1]  # out-of-range labels take the last colour (unlabeled)


def occupancy_cloud_reference(labels: np.ndarray, grid: GridSpec) -> np.ndarray:
    """The definition of `occupancy_cloud`: index arrays of the kept voxels, their centres, palette colours."""
    idx = np.argwhere((labels != EMPTY) & (labels != IGNORE))  # (N, 3) i, j, k
    lab = labels[tuple(idx.T)]
    centres = np.asarray(grid.origin) + (idx + 0.5) * grid.voxel_size
    rgb = PALETTE[np.minimum(lab, len(PALETTE) - 1)].astype(np.uint32)
    cloud = np.zeros(len(idx), LABEL_POINTS)
    cloud["x"], cloud["y"], cloud["z"] = centres.T
    cloud["rgb"] = ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).view(np.float32)
    cloud["label"] = lab
    return cloud


def occupancy_cloud(labels: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(N,) LABEL_POINTS: the centre of every voxel that is neither empty nor ignored, in the grid's frame (C order).

    By table lookups and one pass over the kept voxels: centres per axis are computed once, a voxel's
    x, y, z are three gathers, not index arrays and fancy indexing over the grid (the same bytes as
    `occupancy_cloud_reference`, tested).
    """
    nx, ny, nz = labels.shape
    flat = np.flatnonzero(_SHOWN[labels.ravel()])  # (N,) C-order voxel indices
    lab = labels.reshape(-1)[flat]
    ij, k = np.divmod(flat, nz)
    i, j = np.divmod(ij, ny)
    centres = [(np.arange(n, dtype=np.float64) + 0.5) * grid.voxel_size + o for n, o in zip(labels.shape, grid.origin)]
    cloud = np.zeros(len(flat), LABEL_POINTS)  # zeroed padding: the payload is deterministic
    cloud["x"], cloud["y"], cloud["z"] = centres[0][i], centres[1][j], centres[2][k]
    cloud["rgb"] = _RGB[lab].view(np.float32)
    cloud["label"] = lab
    return cloud
