"""The compiled binning of points is the NumPy definition's, voxel for voxel: points on voxel faces and the grid's
bounds, outside it, NaN and infinite, in rows of more than three columns."""

import numpy as np
import pytest

from co3sop_nodes import kernels
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.inference.inputs import lidar_occupancy, lidar_occupancy_reference
from co3sop_nodes.kernels import point_occupancy

GRID = GridSpec((-25.6, -25.6, -2.0), 0.2, (256, 256, 24))  # the 51.2 m LiDAR grid
EXACT = GridSpec((-16.0, -16.0, -2.0), 0.25, (128, 128, 16))  # faces exact in float32: points land on them exactly


def hostile_points(n: int, columns: int, seed: int, grid: GridSpec = GRID) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(grid.origin), np.asarray(grid.origin) + np.asarray(grid.dims) * grid.voxel_size
    points = rng.normal(0, 10, (n, columns)).astype(np.float32)  # columns beyond x, y, z: anything
    points[:, :3] = rng.uniform(lo - 2, hi + 2, (n, 3))  # a margin outside the grid
    faces = (lo + rng.integers(0, np.asarray(grid.dims) + 1, (n // 4, 3)) * grid.voxel_size).astype(np.float32)
    step = rng.integers(-1, 2, faces.shape).astype(np.float32)  # on a face, or the next float32 either side of it
    points[: n // 4, :3] = np.nextafter(faces, faces + step)
    specials = [np.nan, np.inf, -np.inf, 0.0, -0.0, 1e30]
    for axis in range(3):  # one coordinate at a time, the others inside
        rows = slice(n // 4 + 6 * axis, n // 4 + 6 * axis + 6)
        points[rows, :3] = 0.0
        points[rows, axis] = specials
    points[-3:, :3] = np.nextafter(hi.astype(np.float32), np.float32(-np.inf))  # just inside the far bounds
    return points


@pytest.mark.parametrize("grid", [GRID, EXACT], ids=["51.2m", "exact-faces"])
@pytest.mark.parametrize("columns", [3, 4])
def test_equals_the_definition(columns, grid):
    points = hostile_points(200_000, columns, columns, grid)
    assert point_occupancy.available() and point_occupancy.fits(points)
    got = lidar_occupancy(points, grid)
    np.testing.assert_array_equal(got, lidar_occupancy_reference(points, grid))
    assert got.shape == (1, *grid.dims) and got.dtype == np.uint8 and 0 < got.sum() < len(points)


def test_columns_of_a_wider_array_and_other_dtypes_take_the_definition(monkeypatch):
    wide = hostile_points(5_000, 6, 7)
    view = wide[:, 2:5]  # x, y, z two columns in: rows still whole in memory, one after another
    assert point_occupancy.fits(view)
    np.testing.assert_array_equal(lidar_occupancy(view, GRID), lidar_occupancy_reference(view, GRID))
    assert not point_occupancy.fits(wide[:, :3].astype(np.float64)) and not point_occupancy.fits(wide[::2, :3].T)
    np.testing.assert_array_equal(lidar_occupancy(wide.astype(np.float64), GRID), lidar_occupancy_reference(wide, GRID))
    monkeypatch.setattr(kernels, "ENABLED", False)
    assert not point_occupancy.available()
    np.testing.assert_array_equal(lidar_occupancy(wide, GRID), lidar_occupancy_reference(wide, GRID))


def test_no_points_and_every_point_outside():
    assert lidar_occupancy(np.zeros((0, 3), np.float32), GRID).sum() == 0
    assert lidar_occupancy(np.full((10, 3), 1e6, np.float32), GRID).sum() == 0
