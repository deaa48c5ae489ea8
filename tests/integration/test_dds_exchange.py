"""Two OS processes exchange VoxelFeatures and SemanticOccupancy over real DDS."""

from __future__ import annotations

import json
import sys

import numpy as np
import rclpy
from executables import HERE, finish
from test_node_faults import T0, acked, wait_subscribed

from co3sop_msgs.msg import RequestMap
from co3sop_nodes.common import topics
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.messages import request_msg, stamp_ns
from co3sop_nodes.model.config import preset
from co3sop_nodes.ros.dds import REQUEST_QOS
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.v2x.codec import encode_request
from co3sop_nodes.v2x.sender_requests import MAPS_PER_EGO

sys.path.insert(0, str(HERE / "peers"))
from cases import CASES, encoded
from digest import decoded_digest


def test_every_payload_decodes_bit_exact_in_another_process(processes, tmp_path):
    out = tmp_path / "received.json"
    receiver = processes.peer("exchange.py", "receive", str(out))
    publisher = processes.peer("exchange.py", "publish")
    code, log = finish(publisher)
    assert code == 0, log
    code, log = finish(receiver)
    assert code == 0, log
    received = {int(k): v for k, v in json.loads(out.read_text()).items()}
    assert sorted(received) == list(range(len(CASES)))
    largest = 0
    for index in range(len(CASES)):
        enc = encoded(index)
        assert received[index]["payload_bytes"] == enc.payload_bytes, f"case {index}"
        assert received[index]["digest"] == decoded_digest(enc), f"case {index} decoded differently"
        largest = max(largest, enc.payload_bytes)
    assert largest >= 4 * 1024 * 1024  # the multi-megabyte payloads really crossed


def test_request_maps_sent_while_a_vehicle_is_busy_all_reach_it(peer):
    """An ego ahead of a vehicle sends a map a frame; the vehicle's executor may take none of them for a while (it
    encodes), yet it must still get the map made for each frame it has yet to answer: DDS holds as many as it keeps."""
    grid = preset("tiny", range="51.2m").feature_grid
    need = encode_request(np.ones(grid.dims, np.float32), grid)
    ego = peer.create_publisher(RequestMap, topics.EGO_REQUEST, REQUEST_QOS)
    vehicle = rclpy.create_node("busy_vehicle")
    try:
        got: list[int] = []
        vehicle.create_subscription(
            RequestMap, topics.EGO_REQUEST, lambda m: got.append(stamp_ns(m.header.stamp)), REQUEST_QOS
        )
        wait_subscribed(peer, [ego])
        stamps = [T0 + k * 100_000_000 for k in range(MAPS_PER_EGO)]
        for stamp in stamps:  # the vehicle's executor takes nothing meanwhile
            ego.publish(request_msg(RCLPY, need, stamp_ns=stamp, frame_id="cav_1/lidar", agent_id=1, pose=Pose()))
        acked(ego)
        for _ in range(100):  # all are held: a few turns take them
            rclpy.spin_once(vehicle, timeout_sec=0.1)
            if len(got) == len(stamps):
                break
        assert got == stamps
    finally:
        vehicle.destroy_node()
