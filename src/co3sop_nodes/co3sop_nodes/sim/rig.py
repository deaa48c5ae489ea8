"""OPV2V's sensor rig: where the four cameras and the LiDAR sit on a CAV.

Mounts are given in the vehicle frame with REP-103 axes (x forward, y left,
z up), converted from OpenCDA's CARLA mounts (x forward, y right): camera0
front (2.5, 0, 1.0) yaw 0; camera1 right (0, 0.3, 1.8) yaw 100; camera2 left
(0, -0.3, 1.8) yaw -100; camera3 back (-2.0, 0, 1.5) yaw 180; LiDAR
(-0.5, 0, 1.9) (see src/co3sop_nodes/doc/opv2v-format.md). Flipping y negates
the yaws.
"""

from __future__ import annotations

import numpy as np

CAMERA_NAMES = ("camera0", "camera1", "camera2", "camera3")  # front, right, left, back
_CAMERA_MOUNTS = (  # x, y, z (m), yaw (deg), REP-103
    (2.5, 0.0, 1.0, 0.0),
    (0.0, -0.3, 1.8, -100.0),
    (0.0, 0.3, 1.8, 100.0),
    (-2.0, 0.0, 1.5, 180.0),
)
LIDAR_MOUNT = (-0.5, 0.0, 1.9)
CAMERA_FOV_DEG = 100.0
FULL_RESOLUTION = (800, 600)  # OPV2V's images: width, height


def _transform(x: float, y: float, z: float, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    return np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, z], [0, 0, 0, 1.0]])


def vehicle_from_lidar() -> np.ndarray:
    """4x4 pose of the LiDAR in the vehicle frame."""
    return _transform(*LIDAR_MOUNT)


def vehicle_from_cameras() -> list[np.ndarray]:
    """4x4 poses of camera0..3 in the vehicle frame (camera body axes: x along the view, z up)."""
    return [_transform(*m) for m in _CAMERA_MOUNTS]


def intrinsics(width: int, height: int, fov_deg: float = CAMERA_FOV_DEG) -> np.ndarray:
    """3x3 pinhole matrix as CARLA builds it: f = w / (2 tan(fov / 2)), centre at (w/2, h/2)."""
    f = width / (2.0 * np.tan(np.radians(fov_deg) / 2.0))
    return np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]])
