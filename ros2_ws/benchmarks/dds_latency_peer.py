"""One side of the DDS latency benchmark (run by bench_codec_dds.py, one OS process each).

    dds_latency_peer.py send SIZE COUNT RATE {default,shipped}
    dds_latency_peer.py receive COUNT OUT.json {default,shipped}

The sender stamps each VoxelFeatures (SIZE payload bytes, codec "none") with
CLOCK_REALTIME just before publish; the receiver takes the difference at its
callback (after deserialization), so the figure is one-way latency as an
application sees it. Both processes share the host's clock.
"""

from __future__ import annotations

import json
import os
import sys
import time

# Pick the Fast DDS set-up before rclpy creates a participant.
if sys.argv[-1] == "default":
    os.environ.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
else:
    from co3sop_nodes.ros.dds import configure_environment

    configure_environment()

import rclpy
from rclpy.node import Node

from co3sop_msgs.msg import VoxelFeatures
from co3sop_nodes.messages import stamp_ns, time_msg
from co3sop_nodes.ros.dds import FEATURES_QOS
from co3sop_nodes.ros.message_types import RCLPY

TOPIC = "/bench/latency"


def send(node: Node, size: int, count: int, rate: float) -> None:
    pub = node.create_publisher(VoxelFeatures, TOPIC, FEATURES_QOS)
    while pub.get_subscription_count() == 0:
        time.sleep(0.02)
    time.sleep(0.5)  # let discovery settle on both sides
    msg = VoxelFeatures(codec="none", dtype="float32", values_raw_size=size)
    msg.values = os.urandom(size)
    for _ in range(count + 5):  # a few extra in case the first ones are slow to match
        msg.header.stamp = time_msg(RCLPY, time.time_ns())
        pub.publish(msg)
        time.sleep(1.0 / rate)
    time.sleep(1.0)


def receive(node: Node, count: int, out: str) -> None:
    latencies: list[float] = []

    def on_msg(msg: VoxelFeatures) -> None:
        latencies.append((time.time_ns() - stamp_ns(msg.header.stamp)) / 1e6)

    node.create_subscription(VoxelFeatures, TOPIC, on_msg, FEATURES_QOS)
    deadline = time.monotonic() + 120
    while len(latencies) < count + 5 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    with open(out, "w") as f:
        json.dump(latencies[5:], f)  # drop the warm-up messages


def main() -> None:
    rclpy.init()
    node = Node(f"latency_{sys.argv[1]}")
    try:
        if sys.argv[1] == "send":
            send(node, int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))
        else:
            receive(node, int(sys.argv[2]), sys.argv[3])
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
