"""StaticTransforms: lookups along and across branches of a mount tree."""

import numpy as np
import pytest

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.common.transforms import StaticTransforms


def tree() -> StaticTransforms:
    t = StaticTransforms()
    t.add("base", "lidar", Pose((1.0, 0.0, 1.8)).matrix())
    t.add("lidar", "cam", Pose((0.5, 0.2, -0.1), (0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4))).matrix())
    t.add("base", "imu", Pose((-1.0, 0.0, 0.5)).matrix())
    return t


def test_lookup_composes_the_chain_and_inverts_across_branches():
    t = tree()
    base_from_cam = t.lookup("base", "cam")
    assert np.allclose(base_from_cam[:3, 3], [1.5, 0.2, 1.7])
    point_in_cam = np.array([1.0, 0.0, 0.0, 1.0])  # 1 m along the camera's x, which is the base's y
    assert np.allclose(base_from_cam @ point_in_cam, [1.5, 1.2, 1.7, 1.0])
    imu_from_cam = t.lookup("imu", "cam")
    assert np.allclose(imu_from_cam, np.linalg.inv(t.lookup("base", "imu")) @ base_from_cam)
    assert np.allclose(t.lookup("cam", "cam"), np.eye(4))
    assert "cam" in t and "base" in t and "nowhere" not in t


def test_unconnected_frames_are_an_error_naming_them():
    with pytest.raises(DatasetError, match="'base' and 'other'"):
        tree().lookup("base", "other")
