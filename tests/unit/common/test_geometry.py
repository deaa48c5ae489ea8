"""Unit tests for co3sop_nodes.common.geometry: poses, quaternions and the CARLA <-> REP-103 boundary.

Every expected value is built independently of the module under test: the
standard right-handed elementary rotations, Rodrigues' formula for quaternions,
and the ROS-bridge convention for CARLA transforms.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from co3sop_nodes.common.geometry import (
    Pose,
    carla_matrix_to_pose,
    carla_pose_to_matrix,
    carla_to_ros_grid,
    carla_to_ros_matrix,
    carla_to_ros_points,
    quaternion_to_rotation,
    ros_to_carla_grid,
    ros_to_carla_matrix,
    ros_to_carla_points,
    rotation_to_quaternion,
    yaw_of,
)
from co3sop_nodes.common.grid import GridSpec

# --- independent references ---------------------------------------------------------------------


def rx(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def homogeneous(r: np.ndarray, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


def rodrigues(axis, angle: float) -> np.ndarray:
    """Rotation by `angle` (rad) about the unit vector `axis`."""
    x, y, z = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def quaternion_from_axis_angle(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.array([*(a * math.sin(angle / 2)), math.cos(angle / 2)])


def same_rotation_quaternions(q1, q2, atol=1e-9) -> bool:
    q1, q2 = np.asarray(q1, float), np.asarray(q2, float)
    return bool(np.allclose(q1, q2, atol=atol) or np.allclose(q1, -q2, atol=atol))


def wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def assert_proper_rotation(r: np.ndarray, atol=1e-12) -> None:
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=atol)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=atol)


# --- strategies ---------------------------------------------------------------------------------

angle = st.floats(-180.0, 180.0, allow_nan=False)
pitch_inside = st.floats(-89.0, 89.0, allow_nan=False)
coord = st.floats(-1000.0, 1000.0, allow_nan=False)
unit_axis = st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 3).filter(lambda v: np.linalg.norm(v) > 1e-3)


# --- CARLA pose -> matrix -----------------------------------------------------------------------


@given(coord, coord, coord, angle, angle, angle)
def test_carla_pose_to_matrix_is_rz_yaw_ry_minus_pitch_rx_minus_roll(x, y, z, roll, yaw, pitch):
    m = carla_pose_to_matrix([x, y, z, roll, yaw, pitch])
    assert m.shape == (4, 4)
    np.testing.assert_allclose(m[:3, :3], rz(yaw) @ ry(-pitch) @ rx(-roll), atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], [x, y, z], atol=0)
    np.testing.assert_array_equal(m[3], [0, 0, 0, 1])
    assert_proper_rotation(m[:3, :3])


def test_carla_pose_to_matrix_known_values():
    # CARLA yaw 90: x axis turns to CARLA +y (to the right of the original heading)
    np.testing.assert_allclose(carla_pose_to_matrix([0, 0, 0, 0, 90, 0])[:3, 0], [0, 1, 0], atol=1e-12)
    # CARLA pitch 90 (nose up): x axis points up
    np.testing.assert_allclose(carla_pose_to_matrix([0, 0, 0, 0, 0, 90])[:3, 0], [0, 0, 1], atol=1e-12)
    # argument order is [x, y, z, roll, yaw, pitch]
    np.testing.assert_allclose(carla_pose_to_matrix([1, 2, 3, 0, 0, 0]), homogeneous(np.eye(3), [1, 2, 3]), atol=0)


@given(coord, coord, coord, angle, angle, pitch_inside)
def test_carla_matrix_to_pose_inverts_pose_to_matrix(x, y, z, roll, yaw, pitch):
    pose = carla_matrix_to_pose(carla_pose_to_matrix([x, y, z, roll, yaw, pitch]))
    assert len(pose) == 6 and all(isinstance(v, float) for v in pose)
    np.testing.assert_allclose(pose[:3], [x, y, z], atol=1e-9)
    # angles are returned in (-180, 180]: compare on the circle
    assert wrap_deg(pose[3] - roll) == pytest.approx(0.0, abs=1e-7)
    assert wrap_deg(pose[4] - yaw) == pytest.approx(0.0, abs=1e-7)
    assert pose[5] == pytest.approx(pitch, abs=1e-7)


@given(coord, coord, coord, angle, angle, st.floats(-179.0, 179.0).filter(lambda p: abs(abs(p) - 90) > 1))
def test_carla_matrix_round_trip_for_any_pitch(x, y, z, roll, yaw, pitch):
    # outside (-90, 90) the angles differ, but they describe the same matrix
    m = carla_pose_to_matrix([x, y, z, roll, yaw, pitch])
    np.testing.assert_allclose(carla_pose_to_matrix(carla_matrix_to_pose(m)), m, atol=1e-9)


# --- CARLA -> REP-103 ---------------------------------------------------------------------------


@given(coord, coord, coord, angle, angle, angle)
def test_carla_to_ros_matrix_is_ros_bridge_convention(x, y, z, roll, yaw, pitch):
    ros = carla_to_ros_matrix(carla_pose_to_matrix([x, y, z, roll, yaw, pitch]))
    # REP-103 roll = roll, pitch = -pitch, yaw = -yaw; R = Rz(yaw) Ry(pitch) Rx(roll); y negated
    expected = homogeneous(rz(-yaw) @ ry(-pitch) @ rx(roll), [x, -y, z])
    np.testing.assert_allclose(ros, expected, atol=1e-9)
    assert_proper_rotation(ros[:3, :3])


def test_carla_to_ros_matrix_known_heading():
    # a CARLA actor at CARLA (10, 5) heading CARLA yaw 90 (towards CARLA +y, i.e. to the right)
    ros = carla_to_ros_matrix(carla_pose_to_matrix([10, 5, 1, 0, 90, 0]))
    np.testing.assert_allclose(ros[:3, 3], [10, -5, 1], atol=1e-12)
    np.testing.assert_allclose(ros[:3, 0], [0, -1, 0], atol=1e-12)  # REP-103: to the right is -y
    assert yaw_of(ros) == pytest.approx(-math.pi / 2, abs=1e-12)


@given(st.tuples(coord, coord, coord, angle, angle, angle), st.tuples(coord, coord, coord, angle, angle, angle))
def test_carla_to_ros_matrix_is_a_homomorphism_and_an_involution(a, b):
    ma, mb = carla_pose_to_matrix(a), carla_pose_to_matrix(b)
    np.testing.assert_allclose(
        carla_to_ros_matrix(ma @ mb), carla_to_ros_matrix(ma) @ carla_to_ros_matrix(mb), atol=1e-6
    )
    np.testing.assert_allclose(ros_to_carla_matrix(carla_to_ros_matrix(ma)), ma, atol=0)
    np.testing.assert_allclose(
        carla_to_ros_matrix(np.linalg.inv(ma)), np.linalg.inv(carla_to_ros_matrix(ma)), atol=1e-6
    )


@given(
    st.tuples(coord, coord, coord, angle, angle, angle),
    st.lists(st.tuples(coord, coord, coord), min_size=1, max_size=8),
)
def test_points_and_matrices_convert_consistently(pose, pts):
    # transforming then converting equals converting then transforming
    m = carla_pose_to_matrix(pose)
    p = np.array(pts, float)
    carla_world = p @ m[:3, :3].T + m[:3, 3]
    ros_m = carla_to_ros_matrix(m)
    ros_world = carla_to_ros_points(p).astype(float) @ ros_m[:3, :3].T + ros_m[:3, 3]
    np.testing.assert_allclose(ros_world, carla_to_ros_points(carla_world), rtol=1e-5, atol=1e-2)


def test_carla_to_ros_points_negates_y_keeps_extra_columns():
    pts = np.array([[1.0, 2.0, 3.0, 0.5, 7.0], [-4.0, -5.5, 6.0, 0.25, 8.0]])
    before = pts.copy()
    out = carla_to_ros_points(pts)
    assert out.shape == pts.shape and out.dtype == np.float32
    np.testing.assert_array_equal(out, [[1, -2, 3, 0.5, 7], [-4, 5.5, 6, 0.25, 8]])
    np.testing.assert_array_equal(pts, before)  # input untouched
    np.testing.assert_array_equal(ros_to_carla_points(out), pts.astype(np.float32))
    assert carla_to_ros_points(np.zeros((0, 4))).shape == (0, 4)


def test_carla_to_ros_points_does_not_alias_float32_input():
    pts = np.array([[1.0, 2.0, 3.0]], np.float32)
    out = carla_to_ros_points(pts)
    out[0, 0] = 99
    assert pts[0, 1] == 2.0 and pts[0, 0] == 1.0


def test_carla_to_ros_grid_reverses_y_and_is_an_involution():
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 24, (5, 7, 3)).astype(np.uint8)
    out = carla_to_ros_grid(labels)
    assert out.shape == labels.shape and out.dtype == labels.dtype and out.flags.c_contiguous
    for j in range(7):
        np.testing.assert_array_equal(out[:, j, :], labels[:, 6 - j, :])
    np.testing.assert_array_equal(ros_to_carla_grid(out), labels)
    assert not np.array_equal(out, labels)


@given(
    st.integers(1, 12),
    st.integers(1, 12),
    st.sampled_from([0.1, 0.2, 0.3, 0.4]),
    st.integers(0, 10**6),
)
def test_carla_to_ros_grid_maps_voxel_at_y_to_voxel_at_minus_y(n_half, nz, voxel, pick):
    grid = GridSpec.centred(2 * n_half * voxel, (-2.0, -2.0 + nz * voxel), voxel)
    nx, ny, _ = grid.dims
    i, j, k = np.unravel_index(pick % grid.num_voxels, grid.dims)
    labels = np.zeros(grid.dims, np.uint8)
    labels[i, j, k] = 7
    ((i2, j2, k2),) = np.argwhere(carla_to_ros_grid(labels))
    assert (i2, k2) == (i, k)
    y = grid.origin[1] + (j + 0.5) * voxel
    y2 = grid.origin[1] + (j2 + 0.5) * voxel
    assert y2 == pytest.approx(-y, abs=1e-9)
    # and a CARLA point inside that voxel lands in the converted voxel once converted to REP-103
    point = np.array(
        [[grid.origin[0] + (i + 0.3) * voxel, grid.origin[1] + (j + 0.8) * voxel, grid.origin[2] + (k + 0.5) * voxel]]
    )
    ros = carla_to_ros_points(point)[0].astype(float)
    assert int(math.floor((ros[1] - grid.origin[1]) / voxel)) == j2


# --- quaternions and Pose -----------------------------------------------------------------------


@given(unit_axis, st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False))
def test_quaternion_to_rotation_matches_rodrigues(axis, theta):
    q = quaternion_from_axis_angle(axis, theta)
    np.testing.assert_allclose(quaternion_to_rotation(q), rodrigues(axis, theta), atol=1e-12)
    # a quaternion is normalised first: any positive scale gives the same rotation
    np.testing.assert_allclose(quaternion_to_rotation(3.7 * q), rodrigues(axis, theta), atol=1e-12)


@given(unit_axis, st.floats(0.0, math.pi, allow_nan=False))
def test_rotation_to_quaternion_inverts(axis, theta):
    r = rodrigues(axis, theta)
    q = rotation_to_quaternion(r)
    assert isinstance(q, tuple) and len(q) == 4
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)
    assert q[3] >= 0
    assert same_rotation_quaternions(q, quaternion_from_axis_angle(axis, theta), atol=1e-9)
    np.testing.assert_allclose(quaternion_to_rotation(q), r, atol=1e-9)


@given(unit_axis, st.floats(0.0, 1e-3, allow_nan=False))
def test_rotation_to_quaternion_near_180_degrees(axis, delta):
    # the trace is about -1 here: the branch that picks the largest diagonal element
    for theta in (math.pi - delta, math.pi):
        r = rodrigues(axis, theta)
        q = rotation_to_quaternion(r)
        assert q[3] >= 0
        assert same_rotation_quaternions(q, quaternion_from_axis_angle(axis, theta), atol=1e-8)
        np.testing.assert_allclose(quaternion_to_rotation(q), r, atol=1e-9)


@pytest.mark.parametrize(
    "r",
    [
        np.diag([1.0, -1.0, -1.0]),
        np.diag([-1.0, 1.0, -1.0]),
        np.diag([-1.0, -1.0, 1.0]),
        np.eye(3),
        rz(90),
        ry(-90),
        rx(180) @ rz(90),
    ],
)
def test_rotation_to_quaternion_exact_cases(r):
    q = rotation_to_quaternion(r)
    np.testing.assert_allclose(quaternion_to_rotation(q), r, atol=1e-12)


@given(
    st.tuples(coord, coord, coord),
    st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 4).filter(lambda q: np.linalg.norm(q) > 1e-2),
)
def test_pose_matrix_round_trip(position, quat):
    q = np.asarray(quat) / np.linalg.norm(quat)
    pose = Pose(position, tuple(q))
    m = pose.matrix()
    assert m.shape == (4, 4)
    np.testing.assert_array_equal(m[3], [0, 0, 0, 1])
    np.testing.assert_allclose(m[:3, 3], position, atol=0)
    assert_proper_rotation(m[:3, :3], atol=1e-9)
    back = Pose.from_matrix(m)
    assert all(isinstance(v, float) for v in back.position + back.orientation)
    np.testing.assert_allclose(back.position, position, atol=0)
    assert same_rotation_quaternions(back.orientation, q, atol=1e-8)
    np.testing.assert_allclose(back.matrix(), m, atol=1e-9)


@given(st.tuples(coord, coord, coord), unit_axis, st.floats(math.pi - 1e-4, math.pi, allow_nan=False))
def test_pose_from_matrix_near_half_turn(position, axis, theta):
    m = homogeneous(rodrigues(axis, theta), position)
    np.testing.assert_allclose(Pose.from_matrix(m).matrix(), m, atol=1e-8)


def test_pose_defaults_identity():
    np.testing.assert_array_equal(Pose().matrix(), np.eye(4))
    assert Pose.from_matrix(np.eye(4)) == Pose()


# --- yaw_of -------------------------------------------------------------------------------------


@given(st.floats(-179.9, 179.9), pitch_inside, angle, st.tuples(coord, coord, coord))
def test_yaw_of_is_heading_of_x_axis(yaw, pitch, roll, t):
    m = homogeneous(rz(yaw) @ ry(pitch) @ rx(roll), t)
    assert yaw_of(m) == pytest.approx(math.radians(yaw), abs=1e-9)
    assert yaw_of(m[:3, :3]) == pytest.approx(math.radians(yaw), abs=1e-9)


@given(angle, st.floats(-179.9, 179.9), pitch_inside)
def test_yaw_of_ros_pose_is_minus_carla_yaw(roll, yaw, pitch):
    ros = carla_to_ros_matrix(carla_pose_to_matrix([0, 0, 0, roll, yaw, pitch]))
    assert yaw_of(ros) == pytest.approx(math.radians(wrap_deg(-yaw)), abs=1e-9)
