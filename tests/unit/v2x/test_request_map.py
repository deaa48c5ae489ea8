"""Request maps: the ego's need, and that need carried into a neighbour's frame by the features' warp."""

from __future__ import annotations

import numpy as np
import torch

from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.v2x.request_map import request_for_neighbour, request_of

GRID = GridSpec((-8.0, -8.0, -2.0), 1.0, (16, 16, 4))


def pose(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def test_request_is_one_minus_confidence():
    conf = torch.rand(1, 1, *GRID.dims)
    np.testing.assert_allclose(request_of(conf), 1 - conf[0, 0].numpy(), atol=1e-7)
    assert request_of(conf).dtype == np.float32


def test_request_moves_into_the_neighbours_frame():
    request = np.zeros(GRID.dims, np.float32)
    request[10, 3, :] = 1.0  # the ego needs the column at x = 2.5, y = -4.5 (voxel centres)
    world_from_ego = pose(100.0, 50.0, 0.3)
    # a neighbour 3 m ahead of the ego along the ego's x axis, same heading: that column is at x = -0.5 for it
    world_from_neighbour = world_from_ego @ pose(3.0)
    seen = request_for_neighbour(request, world_from_ego, world_from_neighbour, GRID)
    assert seen.shape == GRID.dims and seen.dtype == np.float32
    np.testing.assert_allclose(seen[7, 3, :], 1.0, atol=1e-5)
    assert abs(seen.sum() - 4.0) < 1e-4  # and nowhere else
    # where the ego's grid does not reach (its last 3 m of x, seen from 3 m further on), the neighbour is asked nothing
    full = request_for_neighbour(np.ones(GRID.dims, np.float32), world_from_ego, world_from_neighbour, GRID)
    assert (full[13:] == 0).all() and (full[:12] == 1).all()
