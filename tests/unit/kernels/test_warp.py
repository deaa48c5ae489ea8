"""Unit tests for co3sop_nodes.kernels.warp: resampling a neighbour's voxel volume on the ego's grid.

Convention under test: volumes are (B, C, X, Y, Z) on a GridSpec (origin = min
corner, voxel centres at origin + (i + 0.5) * voxel_size), and the transform is
T = neighbour_from_ego: the ego voxel centre p_e reads the neighbour's volume at
p_n = T p_e (trilinear, zeros outside the neighbour's grid). The references here
are written from those definitions alone (explicit centres, explicit trilinear
weights); nothing is taken from warp_theta.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.kernels.warp import warp, warp_with_mask

# square in x/y and centred on the sensor: a 90-degree yaw maps the grid onto itself
SQUARE = GridSpec((-2.0, -2.0, -1.0), 0.5, (8, 8, 4))
# deliberately anisotropic and off-centre, so a swapped axis or centre cannot cancel out
ODD = GridSpec((-1.0, -2.2, -0.6), 0.4, (6, 5, 4))


def _transform(rotation: np.ndarray, translation) -> torch.Tensor:
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = translation
    return torch.tensor(t, dtype=torch.float32)


def _yaw(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _centres(grid: GridSpec) -> np.ndarray:
    """(X, Y, Z, 3) voxel centres in metres."""
    axes = [grid.origin[a] + (np.arange(n) + 0.5) * grid.voxel_size for a, n in enumerate(grid.dims)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def _trilinear(volume: np.ndarray, index: np.ndarray) -> np.ndarray:
    """volume (C, X, Y, Z); index (..., 3) continuous voxel indices (centre of voxel i at i) -> (C, ...), zeros outside."""
    dims = np.array(volume.shape[1:])
    base = np.floor(index).astype(int)
    frac = index - base
    out = np.zeros((volume.shape[0],) + index.shape[:-1])
    for corner in np.ndindex(2, 2, 2):
        idx = base + np.array(corner)
        weight = np.prod(np.where(np.array(corner) == 1, frac, 1 - frac), axis=-1)
        inside = np.all((idx >= 0) & (idx < dims), axis=-1)
        safe = np.where(inside[..., None], idx, 0)
        values = volume[:, safe[..., 0], safe[..., 1], safe[..., 2]]
        out += values * (weight * inside)[None]
    return out


def _reference_warp(volume: np.ndarray, neighbour_from_ego: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(C, X, Y, Z) neighbour volume, (4, 4) T_n<-e -> (C, X, Y, Z) on the ego grid."""
    p_e = _centres(grid)
    p_n = p_e @ neighbour_from_ego[:3, :3].T + neighbour_from_ego[:3, 3]
    index = (p_n - np.array(grid.origin)) / grid.voxel_size - 0.5
    return _trilinear(volume, index)


def test_identity_returns_volume():
    torch.manual_seed(0)
    for grid in (SQUARE, ODD):
        vol = torch.randn(2, 3, *grid.dims)
        eye = torch.eye(4).expand(2, 4, 4)
        out, mask = warp_with_mask(vol, eye, grid)
        assert out.shape == vol.shape and mask.shape == (2, 1, *grid.dims)
        torch.testing.assert_close(out, vol, atol=1e-6, rtol=0)
        assert mask.all()
        torch.testing.assert_close(warp(vol, eye, grid), vol, atol=1e-6, rtol=0)


@pytest.mark.parametrize("shift", [(1, 0, 0), (0, 2, 0), (0, 0, 1), (-2, 0, 0), (0, -1, 0), (0, 0, -1), (2, -1, 1)])
@pytest.mark.parametrize("grid", [SQUARE, ODD], ids=["square", "odd"])
def test_integer_translation_shifts_exactly(grid, shift):
    """p_n = p_e + k * voxel: ego voxel i reads neighbour voxel i + k; zeros (mask false) past the grid's end."""
    torch.manual_seed(1)
    vol = torch.randn(1, 2, *grid.dims)
    t = _transform(np.eye(3), np.array(shift) * grid.voxel_size)[None]
    out, mask = warp_with_mask(vol, t, grid)
    expected = torch.zeros_like(vol)
    expected_mask = torch.zeros(1, 1, *grid.dims, dtype=torch.bool)
    nx, ny, nz = grid.dims
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                src = (i + shift[0], j + shift[1], k + shift[2])
                if all(0 <= s < n for s, n in zip(src, grid.dims)):
                    expected[0, :, i, j, k] = vol[0, :, src[0], src[1], src[2]]
                    expected_mask[0, 0, i, j, k] = True
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)
    assert torch.equal(mask, expected_mask)
    assert not expected_mask.all()  # the test does exercise the grid's end


def test_translation_direction_single_voxel():
    """A feature 1 voxel ahead in the neighbour's frame, neighbour 1 voxel ahead of the ego: 2 voxels ahead for the ego."""
    grid = SQUARE
    vol = torch.zeros(1, 1, *grid.dims)
    vol[0, 0, 5, 3, 2] = 1.0  # neighbour frame
    # the neighbour sits 1 voxel ahead of the ego (x_e = x_n + v), so p_n = p_e - (v, 0, 0)
    t = _transform(np.eye(3), (-grid.voxel_size, 0.0, 0.0))[None]
    out = warp(vol, t, grid)
    hot = (out[0, 0] > 0.5).nonzero().tolist()
    assert hot == [[6, 3, 2]]


def test_yaw_90_permutes_voxels():
    """T = R_z(+90 deg): p_n = (-y_e, x_e, z_e), so ego voxel (i, j, k) reads neighbour voxel (n-1-j, i, k)."""
    grid = SQUARE
    n = grid.dims[0]
    torch.manual_seed(2)
    vol = torch.randn(1, 3, *grid.dims)
    t = _transform(_yaw(math.pi / 2), (0.0, 0.0, 0.0))[None]
    out, mask = warp_with_mask(vol, t, grid)
    expected = torch.empty_like(vol)
    for i in range(n):
        for j in range(n):
            expected[0, :, i, j, :] = vol[0, :, n - 1 - j, i, :]
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)
    assert mask.all()


def test_yaw_90_direction_single_voxel():
    """Neighbour yawed +90 deg w.r.t. the ego (T_n<-e = R_z(+90)): what the ego sees ahead (+x_e) lies at +y_n
    (the neighbour's left) in the neighbour's frame."""
    grid = SQUARE
    centres = _centres(grid)
    vol = torch.zeros(1, 1, *grid.dims)
    # neighbour voxel at (x_n, y_n) = (-0.25, +1.75): left of the neighbour, by its own axes
    src = (3, 7, 1)
    vol[0, 0, src[0], src[1], src[2]] = 1.0
    p_n = centres[src]
    assert p_n[1] > 1.5 and abs(p_n[0]) < 0.5
    t = _transform(_yaw(math.pi / 2), (0.0, 0.0, 0.0))[None]
    out = warp(vol, t, grid)
    hot = [tuple(h) for h in (out[0, 0] > 0.5).nonzero().tolist()]
    assert len(hot) == 1
    p_e = centres[hot[0]]
    # p_e = R^-1 p_n: ahead of the ego (x_e = +1.75), slightly right (y_e = +0.25 -> j = 4)
    np.testing.assert_allclose(p_e, [p_n[1], -p_n[0], p_n[2]], atol=1e-9)
    assert hot[0] == (7, 4, 1)


def test_yaw_minus_90_is_inverse_of_plus_90():
    grid = SQUARE
    torch.manual_seed(3)
    vol = torch.randn(1, 2, *grid.dims)
    plus = _transform(_yaw(math.pi / 2), (0, 0, 0))[None]
    minus = _transform(_yaw(-math.pi / 2), (0, 0, 0))[None]
    torch.testing.assert_close(warp(warp(vol, plus, grid), minus, grid), vol, atol=1e-5, rtol=0)
    assert not torch.allclose(warp(vol, plus, grid), warp(vol, minus, grid))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("grid", [SQUARE, ODD], ids=["square", "odd"])
def test_random_rigid_transform_matches_trilinear_reference(grid, seed):
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    b, c = 2, 3
    vol = torch.randn(b, c, *grid.dims)
    mats = []
    for _ in range(b):
        rot = _random_rotation(rng) if seed % 2 else _yaw(rng.uniform(-math.pi, math.pi))
        mats.append(_transform(rot, rng.uniform(-0.6, 0.6, size=3)))
    t = torch.stack(mats)
    out, mask = warp_with_mask(vol, t, grid)
    for n in range(b):
        tn = t[n].double().numpy()
        expected = _reference_warp(vol[n].double().numpy(), tn, grid)
        np.testing.assert_allclose(out[n].numpy(), expected, atol=2e-5, rtol=0)
        coverage = _reference_warp(np.ones((1, *grid.dims)), tn, grid)[0]
        decided = np.abs(coverage - 0.5) > 1e-4  # skip voxels exactly on the mask's threshold
        np.testing.assert_array_equal(mask[n, 0].numpy()[decided], (coverage > 0.5)[decided])
        assert (coverage < 0.5).any()  # part of the ego grid falls outside the neighbour's


def test_nearest_mode_matches_reference_indices():
    """mode='nearest' reads the neighbour voxel that contains p_n."""
    grid = ODD
    torch.manual_seed(7)
    vol = torch.randn(1, 1, *grid.dims)
    t = _transform(_yaw(0.3), (0.13, -0.21, 0.05))
    out = warp(vol, t[None], grid, mode="nearest")[0, 0].numpy()
    p_n = _centres(grid) @ t[:3, :3].double().numpy().T + t[:3, 3].double().numpy()
    idx = np.floor((p_n - np.array(grid.origin)) / grid.voxel_size).astype(int)
    inside = np.all((idx >= 0) & (idx < np.array(grid.dims)), axis=-1)
    safe = np.where(inside[..., None], idx, 0)
    expected = np.where(inside, vol[0, 0].numpy()[safe[..., 0], safe[..., 1], safe[..., 2]], 0.0)
    # skip centres within rounding distance of a voxel boundary
    frac = (p_n - np.array(grid.origin)) / grid.voxel_size
    clear = np.all(np.abs(frac - np.round(frac)) > 1e-4, axis=-1)
    np.testing.assert_allclose(out[clear], expected[clear], atol=1e-6)
    assert inside.any() and (~inside).any() and clear.mean() > 0.9
