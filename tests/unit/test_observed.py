"""learn.observed: a collaborator's LiDAR hits carried into the ego's grid."""

from __future__ import annotations

import numpy as np

from co3sop_nodes.grid import GridSpec
from co3sop_nodes.learn.observed import hits_in_ego_grid, observed_table

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


def test_table_lists_the_share_each_adds():
    result = {"samples": 2, "all": {"voxels": 10, "ego": 0.2, "ego+collaborators": 0.5},
              "classes": {"road": {"voxels": 10, "ego": 0.2, "ego+collaborators": 0.5}}}
    text = observed_table(result, "test, 51.2m")
    assert "| all occupied | 10 | 20.00 | 50.00 | 30.00 |" in text and "| road |" in text
