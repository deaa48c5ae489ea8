"""Occupied voxels as a coloured point list, for PointCloud2 viewers (RViz2, Foxglove) (ROS-free)."""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.classes import EMPTY, IGNORE, PALETTE
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import GridSpec

# x, y, z (float32, m), rgb (float32 holding 0x00RRGGBB, the PCL / RViz convention), label (uint8)
CLOUD_DTYPE = np.dtype({"names": ["x", "y", "z", "rgb", "label"], "formats": ["<f4", "<f4", "<f4", "<f4", "u1"],
                        "offsets": [0, 4, 8, 12, 16], "itemsize": 20})


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
    cloud = np.zeros(len(idx), CLOUD_DTYPE)
    cloud["x"], cloud["y"], cloud["z"] = centres.T
    cloud["rgb"] = ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).view(np.float32)
    cloud["label"] = lab
    return cloud


def occupancy_cloud(labels: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(N,) CLOUD_DTYPE: the centre of every voxel that is neither empty nor ignored, in the grid's frame (C order).

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
    cloud = np.zeros(len(flat), CLOUD_DTYPE)  # zeroed padding: the payload is deterministic
    cloud["x"], cloud["y"], cloud["z"] = centres[0][i], centres[1][j], centres[2][k]
    cloud["rgb"] = _RGB[lab].view(np.float32)
    cloud["label"] = lab
    return cloud


# sensor_msgs/PointField datatypes -> numpy
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
# CLOUD_DTYPE as sensor_msgs/PointField entries: (name, offset, datatype)
CLOUD_FIELDS = [(name, offset, next(d for d, t in _POINT_FIELD_TYPES.items() if np.dtype(t) == dtype))
                for name, (dtype, offset) in CLOUD_DTYPE.fields.items()]


def cloud_xyz(data: bytes, fields: list[tuple[str, int, int]], point_step: int, width: int, height: int = 1) -> np.ndarray:
    """(N, 3) float32 x, y, z of a little-endian PointCloud2 payload; fields: (name, offset, datatype)."""
    layout = {name: (offset, _POINT_FIELD_TYPES.get(datatype)) for name, offset, datatype in fields}
    missing = [a for a in "xyz" if a not in layout or layout[a][1] is None]
    if missing:
        raise DatasetError(f"point cloud has no numeric {', '.join(missing)} field (fields: {', '.join(layout)})")
    n = width * height
    if point_step <= 0 or len(data) < n * point_step:
        raise DatasetError(f"point cloud data holds {len(data)} bytes, {n} points of {point_step} bytes need {n * point_step}")
    dtype = np.dtype({"names": list("xyz"), "formats": [layout[a][1] for a in "xyz"], "offsets": [layout[a][0] for a in "xyz"],
                      "itemsize": point_step})
    cloud = np.frombuffer(data, dtype, count=n)
    return np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(np.float32)
