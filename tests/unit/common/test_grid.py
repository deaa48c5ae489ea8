"""Unit tests for co3sop_nodes.common.grid: GridSpec validation and the paper's benchmark ranges."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from co3sop_nodes.common.errors import Co3sopError, GridError
from co3sop_nodes.common.grid import BENCHMARK_RANGES, BENCHMARK_Z, GridSpec

# name -> (voxel size m, dims): 256 x 256 in x/y, z in [-2.0, 2.8] m
PAPER_RANGES = {
    "25.6m": (0.1, (256, 256, 48)),
    "51.2m": (0.2, (256, 256, 24)),
    "76.8m": (0.3, (256, 256, 16)),
}


def test_benchmark_range_names():
    assert set(BENCHMARK_RANGES) == set(PAPER_RANGES)
    assert BENCHMARK_Z == (-2.0, 2.8)


@pytest.mark.parametrize("name", list(PAPER_RANGES))
def test_benchmark_range_dims_and_voxel_size(name):
    voxel_size, dims = PAPER_RANGES[name]
    grid = BENCHMARK_RANGES[name]
    assert grid.dims == dims
    assert all(type(n) is int for n in grid.dims)
    assert grid.voxel_size == voxel_size
    assert grid.num_voxels == dims[0] * dims[1] * dims[2]


@pytest.mark.parametrize("name", list(PAPER_RANGES))
def test_benchmark_range_extent(name):
    grid = BENCHMARK_RANGES[name]
    side = float(name[:-1])  # "51.2m" -> 51.2
    ex, ey, ez = grid.extent
    assert ex == pytest.approx(side, abs=1e-9) and ey == pytest.approx(side, abs=1e-9)
    assert ez == pytest.approx(4.8, abs=1e-9)
    # x/y symmetric about the sensor
    ox, oy, oz = grid.origin
    assert ox == pytest.approx(-side / 2, abs=1e-9) and oy == pytest.approx(-side / 2, abs=1e-9)
    assert ox + ex == pytest.approx(-ox, abs=1e-9) and oy + ey == pytest.approx(-oy, abs=1e-9)
    # z from -2.0 to 2.8
    assert oz == -2.0
    assert oz + ez == pytest.approx(2.8, abs=1e-9)


def test_benchmark_ranges_are_distinct_frozen_specs():
    grids = list(BENCHMARK_RANGES.values())
    assert len(set(grids)) == 3  # hashable, and all different
    with pytest.raises(dataclasses.FrozenInstanceError):
        grids[0].voxel_size = 1.0  # type: ignore[misc]


def test_num_voxels_and_extent():
    grid = GridSpec((1.0, -2.0, 0.5), 0.25, (4, 3, 2))
    assert grid.num_voxels == 24
    assert grid.extent == (1.0, 0.75, 0.5)


def test_fields_are_normalised():
    grid = GridSpec((0, np.float32(1.5), 2), np.float64(0.5), (np.int64(2), 3, np.uint8(4)))
    assert grid.origin == (0.0, 1.5, 2.0) and all(type(v) is float for v in grid.origin)
    assert type(grid.voxel_size) is float
    assert grid.dims == (2, 3, 4) and all(type(v) is int for v in grid.dims)
    assert grid == GridSpec([0.0, 1.5, 2.0], 0.5, [2, 3, 4])
    assert hash(grid) == hash(GridSpec([0.0, 1.5, 2.0], 0.5, [2, 3, 4]))


def test_centred():
    grid = GridSpec.centred(6.4, (-1.0, 1.0), 0.4)
    assert grid.dims == (16, 16, 5)
    assert grid.origin == pytest.approx((-3.2, -3.2, -1.0))
    assert grid.voxel_size == 0.4


@given(
    n_xy=st.integers(1, 512),
    n_z=st.integers(1, 64),
    voxel_size=st.sampled_from([0.05, 0.1, 0.2, 0.25, 0.3, 0.4, 0.5, 1.0]),
    z0=st.floats(-5, 5, allow_nan=False),
)
def test_centred_round_trips_whole_voxel_counts(n_xy, n_z, voxel_size, z0):
    grid = GridSpec.centred(n_xy * voxel_size, (z0, z0 + n_z * voxel_size), voxel_size)
    assert grid.dims == (n_xy, n_xy, n_z)
    assert grid.origin[0] == grid.origin[1] == pytest.approx(-n_xy * voxel_size / 2)
    assert grid.origin[2] == z0


BAD_GRIDS = {
    "zero voxel": ((0, 0, 0), 0.0, (1, 1, 1)),
    "negative voxel": ((0, 0, 0), -0.1, (1, 1, 1)),
    "nan voxel": ((0, 0, 0), math.nan, (1, 1, 1)),
    "inf voxel": ((0, 0, 0), math.inf, (1, 1, 1)),
    "nan origin": ((0, math.nan, 0), 0.1, (1, 1, 1)),
    "inf origin": ((0, 0, -math.inf), 0.1, (1, 1, 1)),
    "2-d origin": ((0, 0), 0.1, (1, 1, 1)),
    "4-d origin": ((0, 0, 0, 0), 0.1, (1, 1, 1)),
    "zero dim": ((0, 0, 0), 0.1, (1, 0, 1)),
    "negative dim": ((0, 0, 0), 0.1, (-4, 2, 2)),
    "2 dims": ((0, 0, 0), 0.1, (4, 4)),
    "4 dims": ((0, 0, 0), 0.1, (4, 4, 4, 1)),
    "empty dims": ((0, 0, 0), 0.1, ()),
}


@pytest.mark.parametrize("args", list(BAD_GRIDS.values()), ids=list(BAD_GRIDS))
def test_invalid_grid_raises_grid_error(args):
    with pytest.raises(GridError) as info:
        GridSpec(*args)
    assert isinstance(info.value, Co3sopError)
    assert "grid" in str(info.value)


@pytest.mark.parametrize("voxel_size", [-1.0, 0.0, -0.0, math.nan, math.inf, -math.inf])
def test_invalid_centred_grid_raises_grid_error(voxel_size):
    # the core's contract: bad input surfaces as a GridError, never a bare numeric error
    # (ZeroDivisionError, ValueError from round(), OverflowError)
    with pytest.raises(Co3sopError) as info:
        GridSpec.centred(25.6, (-2.0, 2.8), voxel_size)
    assert type(info.value) is GridError, f"{type(info.value).__name__}: {info.value}"
    assert "voxel_size" in str(info.value)


@pytest.mark.parametrize(
    "dims", [(2.5, 1, 1), (1, 1, 0.5), (np.float32(3.25), 2, 2), (math.nan, 1, 1), (1, math.inf, 1)], ids=str
)
def test_non_whole_dims_are_rejected(dims):
    with pytest.raises(GridError) as info:
        GridSpec((0, 0, 0), 0.1, dims)
    assert "dims" in str(info.value)


def test_whole_float_dims_are_accepted():
    grid = GridSpec((0, 0, 0), 0.1, (2.0, np.float64(3.0), 4))
    assert grid.dims == (2, 3, 4) and all(type(v) is int for v in grid.dims)
