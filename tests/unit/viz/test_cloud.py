"""Occupied voxels as coloured points."""

import numpy as np
import pytest

from co3sop_nodes import kernels
from co3sop_nodes.common.classes import IGNORE, PALETTE
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.data.bags import typestore
from co3sop_nodes.kernels import visible_voxels
from co3sop_nodes.messages import LABEL_POINTS, RosbagsTypes, point_cloud_msg, xyz_of
from co3sop_nodes.viz.cloud import occupancy_cloud, occupancy_cloud_reference


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
    assert cloud.dtype == LABEL_POINTS
    msg = point_cloud_msg(RosbagsTypes(typestore()), cloud, stamp_ns=0, frame_id="cav_1/lidar")
    assert np.allclose(xyz_of(msg), [[-0.25, 0.25, 0.75]])


@pytest.mark.parametrize("range_name", sorted(BENCHMARK_RANGES))
@pytest.mark.parametrize("enabled", [True, False], ids=["compiled", "definition"])
def test_the_cloud_equals_its_definition_at_every_range(range_name, enabled, monkeypatch):
    monkeypatch.setattr(kernels, "ENABLED", enabled)
    assert visible_voxels.available() == enabled  # CI machines have a C compiler
    grid = BENCHMARK_RANGES[range_name]
    rng = np.random.default_rng(len(range_name))
    labels = np.where(rng.random(grid.dims) < 0.2, rng.integers(0, 256, grid.dims), 0).astype(
        np.uint8
    )  # every value, out of range too
    want, got = occupancy_cloud_reference(labels, grid), occupancy_cloud(labels, grid)
    assert len(got) > 1000 and got.tobytes() == want.tobytes()  # bit-identical payloads


def test_a_grid_of_one_voxel_and_a_full_grid():
    """Every voxel of a full grid touches its edge or is enclosed; a single voxel is seen from every side."""
    for dims in [(1, 1, 1), (3, 1, 5), (5, 4, 3)]:
        grid = GridSpec((0.0, 0.0, 0.0), 0.4, dims)
        full = np.full(dims, 2, np.uint8)
        got = occupancy_cloud(full, grid)
        inner = int(np.prod([max(n - 2, 0) for n in dims]))
        assert len(got) == full.size - inner
        assert got.tobytes() == occupancy_cloud_reference(full, grid).tobytes()


def test_only_the_voxels_a_viewer_can_see():
    """A solid 5x5x5 block inside the grid shows its shell; a block against the grid's edge shows that face too."""
    grid = GridSpec((0.0, 0.0, 0.0), 1.0, (9, 9, 9))
    labels = np.zeros(grid.dims, np.uint8)
    labels[2:7, 2:7, 2:7] = 4
    cases = [(labels.copy(), 5**3 - 3**3)]
    labels[2:7, 2:7, 4] = IGNORE  # unknown voxels hide nothing: two slabs 2 voxels thick, all seen
    cases.append((labels, 2 * 5 * 5 * 2))
    edge = np.zeros(grid.dims, np.uint8)
    edge[0:3, 2:7, 2:7] = 9  # hidden: x = 1 only (x = 0 is seen from outside the grid), y and z in 3..5
    cases.append((edge, 3 * 5 * 5 - 3 * 3))
    for case, visible in cases:
        got = occupancy_cloud(case, grid)
        assert len(got) == visible
        assert got.tobytes() == occupancy_cloud_reference(case, grid).tobytes()
