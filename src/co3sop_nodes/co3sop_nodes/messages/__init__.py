"""One adapter per message type, shared by the nodes (rclpy) and the bag and recording code (rosbags).

Each message's layout is known here only; a `MessageTypes` (backend.py) says which binding's classes are built.
"""

from co3sop_nodes.messages.backend import MessageTypes, RosbagsTypes, octets_of
from co3sop_nodes.messages.co3sop import (
    FEATURES,
    OCCUPANCY,
    REQUEST,
    features_msg,
    features_of,
    grid_msg,
    grid_of,
    occupancy_msg,
    occupancy_of,
    request_msg,
    request_of,
)
from co3sop_nodes.messages.diagnostics import diagnostics_msg
from co3sop_nodes.messages.sensors import (
    LABEL_POINTS,
    LIDAR_POINTS,
    camera_info_msg,
    image_msg,
    image_of,
    intrinsics_of,
    point_cloud_msg,
    point_fields,
    points_of,
    rgb_of,
    xyz_of,
)
from co3sop_nodes.messages.std import (
    header_msg,
    header_stamp_ns,
    pose_msg,
    pose_of,
    pose_stamped_msg,
    stamp_ns,
    tf_msg,
    time_msg,
    transform_msg,
    transforms_of,
)

__all__ = [
    "FEATURES",
    "LABEL_POINTS",
    "LIDAR_POINTS",
    "OCCUPANCY",
    "REQUEST",
    "MessageTypes",
    "RosbagsTypes",
    "camera_info_msg",
    "diagnostics_msg",
    "features_msg",
    "features_of",
    "grid_msg",
    "grid_of",
    "header_msg",
    "header_stamp_ns",
    "image_msg",
    "image_of",
    "intrinsics_of",
    "occupancy_msg",
    "occupancy_of",
    "octets_of",
    "point_cloud_msg",
    "point_fields",
    "points_of",
    "pose_msg",
    "pose_of",
    "pose_stamped_msg",
    "request_msg",
    "request_of",
    "rgb_of",
    "stamp_ns",
    "tf_msg",
    "time_msg",
    "transform_msg",
    "transforms_of",
    "xyz_of",
]
