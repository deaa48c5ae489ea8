"""Seeded synthetic payloads shaped like the real ones (ROS-free).

Used by the `sample_stream` executable (to check a DDS set-up end to end before
any bag exists), by the DDS tests and by the codec benchmark. The label grid is
a street: road with lane markings, sidewalks, building blocks, parked and
moving vehicles, poles and trees. The feature volume is what an encoder's
output looks like to a codec: spatially smooth channels that are strong near
occupied voxels and near zero in free space, plus a confidence volume.
"""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common import classes
from co3sop_nodes.common.grid import GridSpec


def street_labels(grid: GridSpec, seed: int) -> np.ndarray:
    """(nx, ny, nz) uint8 labels of a random street scene centred on the sensor."""
    rng = np.random.default_rng(seed)
    nx, ny, nz = grid.dims
    v = grid.voxel_size
    x = grid.origin[0] + (np.arange(nx) + 0.5) * v  # voxel centres, m
    y = grid.origin[1] + (np.arange(ny) + 0.5) * v
    z = grid.origin[2] + (np.arange(nz) + 0.5) * v
    labels = np.zeros(grid.dims, np.uint8)
    ground_z = -1.9 + rng.uniform(-0.05, 0.05)  # road surface below the LiDAR, m
    ground = z < ground_z
    half_road = rng.uniform(5.0, 8.0)
    ay = np.abs(y)[None, :]
    surface = np.full((nx, ny), classes.LABEL_BY_NAME["terrain"], np.uint8)
    surface[np.broadcast_to(ay < half_road + 3.0, (nx, ny))] = classes.LABEL_BY_NAME["sidewalk"]
    surface[np.broadcast_to(ay < half_road, (nx, ny))] = classes.LABEL_BY_NAME["road"]
    dashes = (np.abs(y)[None, :] < 0.1) & ((x[:, None] % 6.0) < 3.0)
    surface[dashes] = classes.LABEL_BY_NAME["roadline"]
    labels[:, :, ground] = surface[:, :, None]

    def box(label: str, cx: float, cy: float, sx: float, sy: float, z0: float, z1: float) -> None:
        m = (np.abs(x - cx) < sx / 2)[:, None, None] & (np.abs(y - cy) < sy / 2)[None, :, None]
        labels[m & ((z >= z0) & (z < z1))[None, None, :]] = classes.LABEL_BY_NAME[label]

    extent = max(grid.extent[0], grid.extent[1]) / 2
    for side in (-1, 1):  # building blocks and street furniture on both sides
        cx = -extent
        while cx < extent:
            width = rng.uniform(6, 20)
            box("building", cx + width / 2, side * (half_road + 3 + rng.uniform(2, 6) + 5), width - 1, 10, ground_z, 30)
            cx += width
        for px in np.arange(-extent, extent, rng.uniform(8, 15)):
            kind = rng.choice(["pole", "vegetation", "trafficsign"])
            if kind == "vegetation":
                box("vegetation", px, side * (half_road + 2), 2.5, 2.5, ground_z + 1.5, ground_z + 5)
                box("vegetation", px, side * (half_road + 2), 0.4, 0.4, ground_z, ground_z + 1.5)
            else:
                box("pole", px, side * (half_road + 1), 0.2, 0.2, ground_z, ground_z + 4)
                if kind == "trafficsign":
                    box("trafficsign", px, side * (half_road + 1), 0.1, 0.8, ground_z + 2.5, ground_z + 3.3)
    for _ in range(rng.integers(3, 10)):  # vehicles: car / van / truck sizes
        length, width, height = [(4.5, 1.9, 1.5), (5.5, 2.1, 2.2), (9.0, 2.5, 3.5)][rng.integers(0, 3)]
        lane = rng.choice([-1, 1]) * rng.uniform(1.5, half_road - 1.2)
        box("vehicle", rng.uniform(-extent, extent), lane, length, width, ground_z + 0.2, ground_z + height)
    return labels


def feature_volume(grid: GridSpec, channels: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Smooth (C, nx, ny, nz) float32 features and (nx, ny, nz) confidence in [0, 1]."""
    rng = np.random.default_rng(seed)
    occupied = street_labels(grid, seed) != classes.EMPTY  # (nx, ny, nz)
    coords = np.stack(np.meshgrid(*[np.linspace(0, 1, n) for n in grid.dims], indexing="ij"))  # (3, nx, ny, nz)
    freq = rng.uniform(0.5, 4.0, size=(channels, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(channels, 1, 1, 1))
    waves = np.sin(np.einsum("cd,dxyz->cxyz", freq * 2 * np.pi, coords) + phase)  # (C, nx, ny, nz)
    strength = np.where(occupied, 1.0, 0.05)[None]
    noise = rng.normal(0, 0.02, size=waves.shape)
    features = (rng.uniform(0.5, 2.0, size=(channels, 1, 1, 1)) * waves * strength + noise).astype(np.float32)
    confidence = np.clip(np.where(occupied, 0.8, 0.1) + rng.normal(0, 0.05, size=grid.dims), 0, 1).astype(np.float32)
    return features, confidence
