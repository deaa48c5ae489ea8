"""DDS test peer: `exchange.py publish` sends every case; `exchange.py receive OUT` decodes them.

The two roles run as separate OS processes. The receiver writes a JSON map
case index -> digests of the decoded arrays, and the byte count it received.
"""

from __future__ import annotations

import json
import sys
import time

import rclpy
from cases import CASES, encoded
from digest import decoded_digest
from rclpy.duration import Duration
from rclpy.node import Node

from co3sop_msgs.msg import SemanticOccupancy, VoxelFeatures
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.messages import features_msg, features_of, occupancy_msg, occupancy_of
from co3sop_nodes.ros.dds import FEATURES_QOS, OCCUPANCY_QOS, configure_environment
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.v2x.codec import EncodedFeatures

FEATURES_TOPIC, LABELS_TOPIC = "/test/voxel_features", "/test/occupancy"


def publish(node: Node) -> None:
    pubs = {
        VoxelFeatures: node.create_publisher(VoxelFeatures, FEATURES_TOPIC, FEATURES_QOS),
        SemanticOccupancy: node.create_publisher(SemanticOccupancy, LABELS_TOPIC, OCCUPANCY_QOS),
    }
    deadline = time.monotonic() + 30
    while any(p.get_subscription_count() == 0 for p in pubs.values()):
        if time.monotonic() > deadline:
            sys.exit("publisher: no subscriber matched within 30 s")
        time.sleep(0.05)
    for index in range(len(CASES)):
        enc = encoded(index)
        # header.stamp carries the case index; frame_id names it for humans
        if isinstance(enc, EncodedFeatures):
            msg = features_msg(RCLPY, enc, stamp_ns=index, frame_id=f"case_{index}", agent_id=index, pose=Pose())
        else:
            msg = occupancy_msg(RCLPY, enc, stamp_ns=index, frame_id=f"case_{index}", agent_id=index)
        pub = pubs[type(msg)]
        pub.publish(msg)
        if not pub.wait_for_all_acked(Duration(seconds=30)):
            sys.exit(f"publisher: case {index} not acknowledged within 30 s")
        print(f"publisher: sent case {index}", flush=True)


def receive(node: Node, out_path: str) -> None:
    results: dict[int, dict] = {}

    def on_msg(msg, from_msg):
        enc = from_msg(msg)
        results[msg.header.stamp.nanosec] = {"digest": decoded_digest(enc), "payload_bytes": enc.payload_bytes}

    node.create_subscription(VoxelFeatures, FEATURES_TOPIC, lambda m: on_msg(m, features_of), FEATURES_QOS)
    node.create_subscription(SemanticOccupancy, LABELS_TOPIC, lambda m: on_msg(m, occupancy_of), OCCUPANCY_QOS)
    deadline = time.monotonic() + 90
    while len(results) < len(CASES) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    with open(out_path, "w") as f:
        json.dump({str(k): v for k, v in results.items()}, f)
    print(f"receiver: {len(results)} of {len(CASES)} cases", flush=True)


def main() -> None:
    configure_environment()
    rclpy.init()
    node = Node(f"exchange_{sys.argv[1]}")
    try:
        if sys.argv[1] == "publish":
            publish(node)
        else:
            receive(node, sys.argv[2])
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
