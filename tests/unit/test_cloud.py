"""Occupied voxels as coloured points; PointCloud2 payloads back to x, y, z."""

import numpy as np
import pytest

from co3sop_nodes.common.classes import IGNORE, PALETTE
from co3sop_nodes.viz.cloud import CLOUD_DTYPE, cloud_xyz, occupancy_cloud, occupancy_cloud_reference
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec


def test_occupied_voxel_centres_in_the_palette():
    grid = GridSpec((-1.0, -1.0, 0.0), 0.5, (4, 4, 2))
    labels = np.zeros(grid.dims, np.uint8)
    labels[1, 2, 1] = 7
    labels[3, 0, 0] = IGNORE
    cloud = occupancy_cloud(labels, grid)
    assert len(cloud) == 1 and cloud["label"][0] == 7
    assert np.allclose([cloud["x"][0], cloud["y"][0], cloud["z"][0]], [-0.25, 0.25, 0.75])
    rgb = cloud["rgb"].view(np.uint32)[0]
    assert ((rgb >> 16) & 255, (rgb >> 8) & 255, rgb & 255) == tuple(PALETTE[7])
    fields = [(n, CLOUD_DTYPE.fields[n][1], 7) for n in "xyz"]
    assert np.allclose(cloud_xyz(cloud.tobytes(), fields, CLOUD_DTYPE.itemsize, len(cloud)), [[-0.25, 0.25, 0.75]])


@pytest.mark.parametrize("range_name", sorted(BENCHMARK_RANGES))
def test_the_cloud_equals_its_definition_at_every_range(range_name):
    grid = BENCHMARK_RANGES[range_name]
    rng = np.random.default_rng(len(range_name))
    labels = np.where(rng.random(grid.dims) < 0.2, rng.integers(0, 256, grid.dims), 0).astype(np.uint8)  # every value, out of range too
    want, got = occupancy_cloud_reference(labels, grid), occupancy_cloud(labels, grid)
    assert len(got) > 1000 and got.tobytes() == want.tobytes()  # bit-identical payloads


def test_bad_clouds_are_explained():
    with pytest.raises(DatasetError, match="no numeric z"):
        cloud_xyz(b"\0" * 16, [("x", 0, 7), ("y", 4, 7)], 16, 1)
    with pytest.raises(DatasetError, match="need 32"):
        cloud_xyz(b"\0" * 16, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 16, 2)
