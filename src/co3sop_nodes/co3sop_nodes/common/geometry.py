"""Poses and frames (ROS-free), and the one place where CARLA axes become REP-103.

Every pose and point in this package is in REP-103 axes (x forward, y left,
z up; right-handed), as in ROS messages. OPV2V / CARLA data is left-handed
(x forward, y right, z up) with 6-vector poses [x, y, z, roll, yaw, pitch] in
degrees; `carla_*` functions convert at that boundary and nowhere else:
positions flip y, matrices become S M S with S = diag(1, -1, 1, 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from co3sop_nodes.common.errors import Co3sopError

_FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])
# A camera's optical frame (x right, y down, z along the view) from its body frame (x along the view, y left,
# z up): the rows are the optical axes in body coordinates.
OPTICAL_FROM_BODY = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1.0]])


MAX_POSITION = 1e5  # m: farther from the map origin is a corrupt pose, not a place


@dataclass(frozen=True)
class Pose:
    """A rigid pose: position in m, orientation as a unit quaternion (x, y, z, w)."""

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = quaternion_to_rotation(self.orientation)
        m[:3, 3] = self.position
        return m

    @classmethod
    def from_matrix(cls, m: np.ndarray) -> Pose:
        return cls(tuple(float(v) for v in m[:3, 3]), rotation_to_quaternion(m[:3, :3]))

    def check(self, what: str, max_distance: float = MAX_POSITION) -> None:
        """Raises a Co3sopError naming `what` if the pose is not finite, too far, or not a rotation."""
        p, q = np.asarray(self.position, float), np.asarray(self.orientation, float)
        if not (np.isfinite(p).all() and np.isfinite(q).all()):
            raise Co3sopError(f"{what}: pose is not finite (position {p.tolist()}, orientation {q.tolist()})")
        if np.abs(p).max() > max_distance:
            raise Co3sopError(f"{what}: position {p.tolist()} is more than {max_distance:g} m from the origin")
        if abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise Co3sopError(
                f"{what}: orientation {q.tolist()} is not a unit quaternion (norm {np.linalg.norm(q):.4g})"
            )


def quaternion_to_rotation(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix."""
    m = np.asarray(r, float)
    t = np.trace(m)
    if t > 0:
        s = 2 * np.sqrt(t + 1)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0] * 4
        q[i], q[j], q[k] = s / 4, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    q = np.array(q)
    q = -q if q[3] < 0 else q
    return tuple(float(v) for v in q / np.linalg.norm(q))


def yaw_of(m: np.ndarray) -> float:
    """Heading (rad) of a pose matrix's x axis in the x-y plane."""
    return float(np.arctan2(m[1, 0], m[0, 0]))


# --- CARLA / OPV2V boundary ---------------------------------------------------------------------


def carla_pose_to_matrix(pose) -> np.ndarray:
    """OPV2V [x, y, z, roll, yaw, pitch] (m, deg, CARLA axes) -> 4x4 world_from_x in CARLA axes.

    The matrix is CARLA's Transform.get_matrix(), as OpenCOOD's x_to_world builds it.
    """
    x, y, z, roll, yaw, pitch = (float(v) for v in pose)
    cr, sr = np.cos(np.radians(roll)), np.sin(np.radians(roll))
    cy, sy = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    cp, sp = np.cos(np.radians(pitch)), np.sin(np.radians(pitch))
    return np.array(
        [
            [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr, x],
            [sy * cp, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr, y],
            [sp, -cp * sr, cp * cr, z],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def carla_matrix_to_pose(m: np.ndarray) -> list[float]:
    """Inverse of carla_pose_to_matrix: [x, y, z, roll, yaw, pitch] (m, deg)."""
    pitch = np.degrees(np.arcsin(np.clip(m[2, 0], -1, 1)))
    yaw = np.degrees(np.arctan2(m[1, 0], m[0, 0]))
    roll = np.degrees(np.arctan2(-m[2, 1], m[2, 2]))
    return [float(m[0, 3]), float(m[1, 3]), float(m[2, 3]), float(roll), float(yaw), float(pitch)]


def carla_to_ros_matrix(m: np.ndarray) -> np.ndarray:
    """A 4x4 transform between CARLA-axis frames -> the same transform between REP-103 frames."""
    return _FLIP_Y @ m @ _FLIP_Y


ros_to_carla_matrix = carla_to_ros_matrix  # the mirror is its own inverse


def carla_to_ros_points(points: np.ndarray) -> np.ndarray:
    """(N, 3+) points in a CARLA-axis frame -> REP-103 (y negated; extra columns kept)."""
    out = np.array(points, dtype=np.float32, copy=True)
    out[:, 1] *= -1
    return out


ros_to_carla_points = carla_to_ros_points


def carla_to_ros_grid(labels: np.ndarray) -> np.ndarray:
    """A label grid [x][y][z] in a CARLA-axis sensor frame, centred in y -> REP-103 (y reversed)."""
    return np.ascontiguousarray(labels[:, ::-1, :])


ros_to_carla_grid = carla_to_ros_grid
