"""Voxel grid specifications and the Co3SOP benchmark ranges.

Axis order and frame, for every array in this project: a grid is indexed
[i][j][k] along [x][y][z] of its agent's LiDAR frame in REP-103 axes (x forward,
y left, z up; metres); arrays are shaped (nx, ny, nz), flattened in C order
(z fastest). Feature volumes prepend channels: (C, nx, ny, nz).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from co3sop_nodes.common.errors import GridError


@dataclass(frozen=True)
class GridSpec:
    """A regular axis-aligned grid of cubic voxels."""

    origin: tuple[float, float, float]  # minimum corner of voxel (0, 0, 0), m
    voxel_size: float  # m
    dims: tuple[int, int, int]  # (nx, ny, nz)

    def __post_init__(self) -> None:
        if len(self.origin) != 3 or not all(math.isfinite(v) for v in self.origin):
            raise GridError(f"grid origin must be 3 finite numbers, got {self.origin}")
        _check_voxel_size(self.voxel_size)
        if len(self.dims) != 3 or not all(float(n).is_integer() and n >= 1 for n in self.dims):
            raise GridError(f"grid dims must be 3 positive whole numbers, got {self.dims}")
        object.__setattr__(self, "origin", tuple(float(v) for v in self.origin))
        object.__setattr__(self, "dims", tuple(int(v) for v in self.dims))
        object.__setattr__(self, "voxel_size", float(self.voxel_size))

    @property
    def num_voxels(self) -> int:
        nx, ny, nz = self.dims
        return nx * ny * nz

    @property
    def extent(self) -> tuple[float, float, float]:
        """Side lengths (m) along x, y, z."""
        return tuple(n * self.voxel_size for n in self.dims)

    @classmethod
    def centred(cls, extent_xy: float, z_range: tuple[float, float], voxel_size: float) -> GridSpec:
        """A grid centred on the sensor in x/y, spanning `z_range` in z."""
        _check_voxel_size(voxel_size)
        n_xy = round(extent_xy / voxel_size)
        n_z = round((z_range[1] - z_range[0]) / voxel_size)
        half = n_xy * voxel_size / 2
        return cls((-half, -half, z_range[0]), voxel_size, (n_xy, n_xy, n_z))


def _check_voxel_size(voxel_size: float) -> None:
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise GridError(f"grid voxel_size must be a positive number of metres, got {voxel_size}")


# The paper's three benchmark grids: 256 x 256 in x/y, z in [-2.0, 2.8] m
# relative to the LiDAR, named by their side length.
BENCHMARK_Z = (-2.0, 2.8)
BENCHMARK_RANGES: dict[str, GridSpec] = {
    "25.6m": GridSpec.centred(25.6, BENCHMARK_Z, 0.1),  # 256 x 256 x 48
    "51.2m": GridSpec.centred(51.2, BENCHMARK_Z, 0.2),  # 256 x 256 x 24
    "76.8m": GridSpec.centred(76.8, BENCHMARK_Z, 0.3),  # 256 x 256 x 16
}
