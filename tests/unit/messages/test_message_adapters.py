"""Each message adapter builds the same bytes through rclpy and through rosbags, and reads back what it wrote."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from co3sop_nodes.common.errors import Co3sopError, DatasetError
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.data.bags import typestore
from co3sop_nodes.data.synthetic import feature_volume, street_labels
from co3sop_nodes.messages import (
    LABEL_POINTS,
    LIDAR_POINTS,
    RosbagsTypes,
    camera_info_msg,
    features_msg,
    features_of,
    image_msg,
    image_of,
    intrinsics_of,
    occupancy_msg,
    occupancy_of,
    point_cloud_msg,
    points_of,
    pose_of,
    pose_stamped_msg,
    request_msg,
    request_of,
    rgb_of,
    scan_msg,
    scan_of,
    stamp_ns,
    tf_msg,
    transform_msg,
    transforms_of,
    xyz_of,
)
from co3sop_nodes.ros.message_types import RCLPY, message_class
from co3sop_nodes.v2x.codec import (
    FeatureCodecConfig,
    decode_features,
    decode_labels,
    decode_request,
    encode_features,
    encode_labels,
    encode_request,
)
from co3sop_nodes.v2x.scan import ScanCodecConfig, decode_scan, encode_scan

STORE = typestore()
ROSBAGS = RosbagsTypes(STORE)
GRID = GridSpec((-3.2, -3.2, -1.0), 0.4, (16, 16, 4))
POSE = Pose((1.0, -2.0, 1.8), (0.0, 0.0, 0.38268343, 0.92387953))
AT = {"stamp_ns": 1_700_000_000_123_456_789, "frame_id": "cav_3/lidar"}


def same(a, b) -> bool:
    """Two messages read by rosbags hold the same values (CDR padding bytes are not compared: Fast CDR leaves
    them undefined)."""
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, list):
        return len(a) == len(b) and all(map(same, a, b))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and np.array_equal(a, b)
    return a == b


def both(build, msgtype: str):
    """The message built through each binding; both serialise to the same values. Returns the rosbags and the
    rclpy message, each read back from its own bytes."""
    ours = bytes(STORE.serialize_cdr(build(ROSBAGS), msgtype))
    theirs = serialize_message(build(RCLPY))
    assert same(STORE.deserialize_cdr(ours, msgtype), STORE.deserialize_cdr(theirs, msgtype)), msgtype
    return STORE.deserialize_cdr(ours, msgtype), deserialize_message(theirs, message_class(msgtype))


def test_features_round_trip_through_both_bindings():
    volume, confidence = feature_volume(GRID, 8, 0)
    enc = encode_features(
        volume, confidence, GRID, FeatureCodecConfig(dtype="int8", rank=4, selection="topk", topk=300)
    )
    for msg in both(
        lambda t: features_msg(t, enc, pose=POSE, agent_id=3, recipient_id=5, **AT), "co3sop_msgs/msg/VoxelFeatures"
    ):
        back = features_of(msg)
        assert np.array_equal(decode_features(back).features, decode_features(enc).features)
        assert (msg.addressed, msg.recipient_id, stamp_ns(msg.header.stamp)) == (True, 5, AT["stamp_ns"])
        assert np.allclose(pose_of(msg.lidar_pose).matrix(), POSE.matrix())


def test_scans_round_trip_through_both_bindings():
    occupancy = np.random.default_rng(4).random(GRID.dims) < 0.1
    enc = encode_scan(occupancy, GRID, ScanCodecConfig())
    for msg in both(lambda t: scan_msg(t, enc, pose=POSE, agent_id=3, **AT), "co3sop_msgs/msg/VoxelScan"):
        assert scan_of(msg) == enc and np.array_equal(decode_scan(scan_of(msg)), occupancy)
        assert (msg.agent_id, stamp_ns(msg.header.stamp), msg.header.frame_id) == (3, AT["stamp_ns"], AT["frame_id"])
        assert np.allclose(pose_of(msg.lidar_pose).matrix(), POSE.matrix())


def test_occupancy_and_request_round_trip_through_both_bindings():
    labels = street_labels(GRID, 1)
    enc = encode_labels(labels, GRID, 24)
    for msg in both(lambda t: occupancy_msg(t, enc, agent_id=3, **AT), "co3sop_msgs/msg/SemanticOccupancy"):
        assert np.array_equal(decode_labels(occupancy_of(msg)).labels, labels) and occupancy_of(msg).grid == GRID
    need = np.random.default_rng(2).random(GRID.dims).astype(np.float32)
    req = encode_request(need, GRID, levels=4)
    for msg in both(lambda t: request_msg(t, req, agent_id=3, pose=POSE, **AT), "co3sop_msgs/msg/RequestMap"):
        assert np.array_equal(decode_request(request_of(msg)), decode_request(req))


def test_point_clouds_keep_their_layout():
    cloud = np.zeros(5, LIDAR_POINTS)
    cloud["x"], cloud["y"], cloud["z"], cloud["intensity"], cloud["label"] = 1.5, -2.0, 0.25, 0.5, 7
    for msg in both(lambda t: point_cloud_msg(t, cloud, **AT), "sensor_msgs/msg/PointCloud2"):
        assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
            ("x", 0, 7),
            ("y", 4, 7),
            ("z", 8, 7),
            ("intensity", 12, 7),
            ("label", 16, 2),
        ]
        assert np.allclose(xyz_of(msg), [[1.5, -2.0, 0.25]] * 5)
        assert (points_of(msg, ("label",))["label"] == 7).all()
    labelled = np.zeros(2, LABEL_POINTS)
    rosbags_msg, _ = both(lambda t: point_cloud_msg(t, labelled, **AT), "sensor_msgs/msg/PointCloud2")
    assert [f.name for f in rosbags_msg.fields] == ["x", "y", "z", "rgb", "label"]


def test_clouds_that_do_not_fit_are_explained():
    cloud = point_cloud_msg(ROSBAGS, np.zeros(2, LIDAR_POINTS), **AT)
    with pytest.raises(DatasetError, match="no numeric ring"):
        points_of(cloud, ("x", "ring"))
    cloud.width = 3
    with pytest.raises(DatasetError, match="need 60"):
        xyz_of(cloud)


def test_images_and_camera_info():
    rgb = np.random.default_rng(3).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    depth = np.linspace(0, 80, 48, dtype=np.float32).reshape(6, 8)
    k = np.array([[400.0, 0, 4], [0, 400.0, 3], [0, 0, 1]])
    for msg in both(lambda t: image_msg(t, rgb, "rgb8", **AT), "sensor_msgs/msg/Image"):
        assert np.array_equal(rgb_of(msg, "/cav_3/camera0/image_raw"), rgb)
    for msg in both(lambda t: image_msg(t, depth, "32FC1", **AT), "sensor_msgs/msg/Image"):
        assert np.array_equal(image_of(msg, "depth"), depth)
        with pytest.raises(Co3sopError, match="depth: encoding '32FC1', expected rgb8"):
            rgb_of(msg, "depth")
    for msg in both(lambda t: camera_info_msg(t, k, 8, 6, **AT), "sensor_msgs/msg/CameraInfo"):
        assert np.array_equal(intrinsics_of(msg), k) and (msg.width, msg.height) == (8, 6)


def test_poses_and_transforms():
    m = POSE.matrix()
    for msg in both(lambda t: pose_stamped_msg(t, AT["stamp_ns"], "map", POSE), "geometry_msgs/msg/PoseStamped"):
        assert np.allclose(pose_of(msg.pose).matrix(), m)
    for msg in both(
        lambda t: tf_msg(t, [transform_msg(t, AT["stamp_ns"], "cav_3/base_link", "cav_3/lidar", m)]),
        "tf2_msgs/msg/TFMessage",
    ):
        [(parent, child, got)] = transforms_of(msg)
        assert (parent, child) == ("cav_3/base_link", "cav_3/lidar") and np.allclose(got, m)


def test_an_empty_range_grid_message_is_the_benchmark_grid():
    grid = BENCHMARK_RANGES["51.2m"]
    enc = encode_labels(np.zeros(grid.dims, np.uint8), grid, 24)
    rosbags_msg, rclpy_msg = both(
        lambda t: occupancy_msg(t, enc, agent_id=1, **AT), "co3sop_msgs/msg/SemanticOccupancy"
    )
    assert occupancy_of(rosbags_msg).grid == occupancy_of(rclpy_msg).grid == grid
