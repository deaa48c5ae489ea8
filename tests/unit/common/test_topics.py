"""co3sop_nodes.common.topics: the one place topic names are built and taken apart."""

from __future__ import annotations

import pytest

from co3sop_nodes.common import topics


@pytest.mark.parametrize(
    "build, rest",
    [
        (lambda a: topics.voxel_features(a), "voxel_features"),
        (lambda a: topics.lidar_pose(a), "lidar/pose"),
        (lambda a: topics.lidar_points(a), "lidar/points"),
        (lambda a: topics.camera_image(a, "camera2"), "camera2/image_raw"),
        (lambda a: topics.camera_info(a, "camera0"), "camera0/camera_info"),
        (lambda a: topics.ground_truth(a, "76.8m"), "ground_truth/occupancy_76m"),
    ],
)
@pytest.mark.parametrize("agent", [0, 7, 1234])
def test_split_inverts_every_per_vehicle_builder(build, rest, agent):
    assert topics.split_cav_topic(build(agent)) == (agent, rest)


@pytest.mark.parametrize(
    "topic",
    [
        topics.EGO_OCCUPANCY,
        topics.TF_STATIC,
        topics.DIAGNOSTICS,
        "/cav_x/lidar/pose",
        "/cav_3",
        "cav_3/lidar/pose",
        "/fleet/cav_3/lidar/pose",
    ],
)
def test_other_topics_are_not_per_vehicle(topic):
    assert topics.split_cav_topic(topic) is None
