"""builtin_interfaces/Time, std_msgs/Header, geometry_msgs Pose / PoseStamped / TransformStamped and
tf2_msgs/TFMessage (ROS-free adapters; see backend.py)."""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.messages.backend import MessageTypes

NS = 1_000_000_000


def stamp_ns(stamp) -> int:
    """A builtin_interfaces/Time in ns."""
    return stamp.sec * NS + stamp.nanosec


def time_msg(types: MessageTypes, ns: int):
    return types.make("builtin_interfaces/msg/Time", sec=ns // NS, nanosec=ns % NS)


def header_msg(types: MessageTypes, ns: int, frame_id: str):
    return types.make("std_msgs/msg/Header", stamp=time_msg(types, ns), frame_id=frame_id)


def header_stamp_ns(msg) -> int:
    """A stamped message's header stamp in ns."""
    return stamp_ns(msg.header.stamp)


def pose_msg(types: MessageTypes, pose: Pose):
    return types.make(
        "geometry_msgs/msg/Pose",
        position=types.make("geometry_msgs/msg/Point", x=pose.position[0], y=pose.position[1], z=pose.position[2]),
        orientation=quaternion_msg(types, pose.orientation),
    )


def quaternion_msg(types: MessageTypes, q):
    return types.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])


def pose_of(msg) -> Pose:
    """A geometry_msgs/Pose as a Pose (not checked: Pose.check names what is wrong)."""
    p, o = msg.position, msg.orientation
    return Pose((p.x, p.y, p.z), (o.x, o.y, o.z, o.w))


def pose_stamped_msg(types: MessageTypes, ns: int, frame_id: str, pose: Pose):
    return types.make(
        "geometry_msgs/msg/PoseStamped", header=header_msg(types, ns, frame_id), pose=pose_msg(types, pose)
    )


def transform_msg(types: MessageTypes, ns: int, parent: str, child: str, parent_from_child: np.ndarray):
    """A geometry_msgs/TransformStamped from a 4x4 parent_from_child matrix."""
    pose = Pose.from_matrix(parent_from_child)
    t = pose.position
    transform = types.make(
        "geometry_msgs/msg/Transform",
        translation=types.make("geometry_msgs/msg/Vector3", x=t[0], y=t[1], z=t[2]),
        rotation=quaternion_msg(types, pose.orientation),
    )
    return types.make(
        "geometry_msgs/msg/TransformStamped",
        header=header_msg(types, ns, parent),
        child_frame_id=child,
        transform=transform,
    )


def tf_msg(types: MessageTypes, transforms: list):
    return types.make("tf2_msgs/msg/TFMessage", transforms=transforms)


def transforms_of(msg) -> list[tuple[str, str, np.ndarray]]:
    """A tf2_msgs/TFMessage as (parent, child, 4x4 parent_from_child) triples."""
    out = []
    for t in msg.transforms:
        tr, q = t.transform.translation, t.transform.rotation
        out.append((t.header.frame_id, t.child_frame_id, Pose((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w)).matrix()))
    return out
