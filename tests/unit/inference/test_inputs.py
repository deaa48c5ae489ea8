"""model.inputs: a collaborator's LiDAR occupancy carried into the ego's grid, and an early-fusion model's merged scan."""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.inference.inputs import hits_in_ego_grid, lidar_occupancy, merged_occupancy

GRID = GridSpec((-4.0, -4.0, -1.0), 0.5, (16, 16, 4))


def test_hits_move_with_the_transform_and_leave_the_grid_when_outside():
    occupancy = np.zeros(GRID.dims, np.uint8)
    occupancy[3, 5, 1] = occupancy[15, 0, 0] = 1
    ego_from_neighbour = np.eye(4)
    ego_from_neighbour[:3, 3] = (1.0, -0.5, 0.0)  # the neighbour 2 voxels ahead, 1 to the right of the ego
    hits = np.argwhere(hits_in_ego_grid(occupancy, ego_from_neighbour, GRID))
    assert hits.tolist() == [[5, 4, 1]]  # (15, 0, 0) moves to (17, -1, 0): outside the ego's grid
    turned = np.eye(4)
    turned[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]  # 90 degrees to the left about the shared origin
    np.testing.assert_array_equal(np.argwhere(hits_in_ego_grid(occupancy, turned, GRID)), [[10, 3, 1], [15, 15, 0]])
    np.testing.assert_array_equal(hits_in_ego_grid(occupancy, np.eye(4), GRID), occupancy.astype(bool))


def test_merged_scan_is_the_union_of_the_ego_and_its_collaborators_in_the_ego_grid():
    ego = np.zeros((1, *GRID.dims), np.uint8)
    ego[0, 0, 0, 0] = 1
    near, far = np.zeros_like(ego), np.zeros_like(ego)
    near[0, 3, 5, 1] = 1
    far[0, 8, 8, 2] = 1
    neighbour_from_ego = np.stack([np.eye(4), np.eye(4)])
    neighbour_from_ego[0, :3, 3] = (-1.0, 0.5, 0.0)  # the first neighbour 2 voxels ahead, 1 to the right of the ego
    neighbour_from_ego[1, :3, 3] = (-10.0, 0.0, 0.0)  # the second 10 m ahead: its hit leaves the ego's grid
    merged = merged_occupancy(ego, [near, far], neighbour_from_ego, GRID)
    assert merged.shape == ego.shape and merged.dtype == np.uint8
    assert np.argwhere(merged[0]).tolist() == [[0, 0, 0], [5, 4, 1]]
    np.testing.assert_array_equal(merged_occupancy(ego, [], np.zeros((0, 4, 4)), GRID), ego)  # alone: its own scan
    assert ego.sum() == 1  # the ego's array is not written to


def test_a_scan_marks_the_voxels_its_points_fall_in_and_nothing_outside():
    grid = GridSpec((-2.0, -1.0, 0.0), 0.5, (8, 4, 3))
    points = np.array(
        [
            [-2.0, -1.0, 0.0],  # the first voxel's corner: inside
            [1.99, 0.99, 1.49],  # the last voxel
            [0.1, 0.2, 0.7],  # voxel (4, 2, 1), twice
            [0.2, 0.3, 0.8],
            [-2.01, 0.0, 0.5],  # just outside, one axis each
            [0.0, 1.0, 0.5],
            [0.0, 0.0, 1.5],
            [np.nan, 0.0, 0.5],  # not a point: never a voxel
            [np.inf, 0.0, 0.5],
            [-1e12, 0.0, 0.5],  # beyond int64's range after the division: outside too
        ],
        np.float32,
    )
    occupancy = lidar_occupancy(points, grid)
    assert occupancy.shape == (1, 8, 4, 3) and occupancy.dtype == np.uint8
    assert sorted(map(tuple, np.argwhere(occupancy[0]))) == [(0, 0, 0), (4, 2, 1), (7, 3, 2)]
