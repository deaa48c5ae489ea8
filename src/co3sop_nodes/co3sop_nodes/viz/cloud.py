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
from co3sop_nodes.kernels import visible_voxels
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
    """(N,) LABEL_POINTS: the centre of every voxel a viewer can see (module docstring), in the grid's frame (C order):
    by the compiled kernel where it compiles, the same bytes as `occupancy_cloud_reference` (tested)."""
    if not visible_voxels.available():
        return occupancy_cloud_reference(labels, grid)
    centres = [(np.arange(n, dtype=np.float64) + 0.5) * grid.voxel_size + o for n, o in zip(labels.shape, grid.origin)]
    return visible_voxels.visible_points(labels, centres, _RGB, LABEL_POINTS)
