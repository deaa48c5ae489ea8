"""Label grids larger than a range's, as Co3SOP's sensor may write them: the reader's centre crop gives back the
range's voxels exactly."""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common import geometry as geo
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.data import opv2v
from co3sop_nodes.sim.scenario import labelled_grid


def test_the_margin_grid_holds_the_range_grid_at_its_centre_and_bottom():
    for name, grid in BENCHMARK_RANGES.items():
        big = labelled_grid(grid, (8, 4))
        assert (
            big.dims == (grid.dims[0] + 16, grid.dims[1] + 16, grid.dims[2] + 4) and big.voxel_size == grid.voxel_size
        )
        idx = np.array([[0, 0, 0], [17, 200, 5], [255, 255, grid.dims[2] - 1]])
        inner = np.asarray(grid.origin) + (idx + 0.5) * grid.voxel_size
        outer = np.asarray(big.origin) + (idx + [8, 8, 0] + 0.5) * big.voxel_size
        np.testing.assert_allclose(inner, outer, atol=1e-9, err_msg=name)


def test_the_reader_crops_a_margin_grid_back_to_the_range(tmp_path):
    grid = BENCHMARK_RANGES["51.2m"]
    big = labelled_grid(grid, (8, 4))
    labels = np.random.default_rng(0).integers(0, 24, big.dims).astype(np.uint8)  # REP-103, as the sensor gives them
    path = tmp_path / "000001_voxels.npz"
    np.savez_compressed(path, voxels=geo.ros_to_carla_grid(labels))  # as write_frame writes them
    np.testing.assert_array_equal(opv2v.read_labels(path, "51.2m"), labels[8:-8, 8:-8, : grid.dims[2]])
