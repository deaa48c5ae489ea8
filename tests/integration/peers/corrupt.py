"""DDS test peer: publishes one VoxelFeatures whose values payload is truncated, then a valid one."""

from __future__ import annotations

import sys
import time

import rclpy
from cases import encoded
from rclpy.duration import Duration
from rclpy.node import Node

from co3sop_msgs.msg import VoxelFeatures
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.messages import features_msg
from co3sop_nodes.ros.dds import FEATURES_QOS, configure_environment
from co3sop_nodes.ros.message_types import RCLPY

TOPIC = "/test_corrupt/voxel_features"


def main() -> None:
    configure_environment()
    rclpy.init()
    node = Node("corrupt_publisher")
    try:
        pub = node.create_publisher(VoxelFeatures, TOPIC, FEATURES_QOS)
        deadline = time.monotonic() + 30
        while pub.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                sys.exit("no subscriber matched within 30 s")
            time.sleep(0.05)
        enc = encoded(2)  # float16 top-k features, byte-shuffled and zstd-compressed
        for values in (enc.values[: len(enc.values) // 2], enc.values):
            msg = features_msg(RCLPY, enc, stamp_ns=1, frame_id="cav_9/lidar", agent_id=9, pose=Pose())
            msg.values = bytes(values)
            pub.publish(msg)
            pub.wait_for_all_acked(Duration(seconds=30))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
