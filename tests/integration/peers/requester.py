"""A stand-in ego that only asks: publishes one request map, again every 0.2 s until stopped.

    requester.py EGO_ID STAMP_NS POSE_JSON RANGE [TOPIC]

TOPIC defaults to /ego/request_map (an ego in the root namespace). The need is 1 on the first half of the feature grid along x and 0 elsewhere; the pose is the ego's LiDAR pose
(a 4x4 matrix as JSON) at the stamp. A vehicle with codec.selection request answers it from its first frame on.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import rclpy

from co3sop_msgs.msg import RequestMap
from co3sop_nodes.common import topics
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.messages import request_msg
from co3sop_nodes.model.config import preset
from co3sop_nodes.ros.dds import REQUEST_QOS
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.v2x.codec import encode_request


def main() -> None:
    ego, stamp, matrix, rng = int(sys.argv[1]), int(sys.argv[2]), np.array(json.loads(sys.argv[3])), sys.argv[4]
    topic = sys.argv[5] if len(sys.argv) > 5 else topics.EGO_REQUEST
    grid = preset("tiny", range=rng).feature_grid
    need = np.zeros(grid.dims, np.float32)
    need[: grid.dims[0] // 2] = 1.0
    rclpy.init()
    node = rclpy.create_node("requester")
    pub = node.create_publisher(RequestMap, topic, REQUEST_QOS)
    msg = request_msg(
        RCLPY,
        encode_request(need, grid),
        stamp_ns=stamp,
        frame_id=topics.lidar_frame(ego),
        agent_id=ego,
        pose=Pose.from_matrix(matrix),
    )
    node.create_timer(0.2, lambda: pub.publish(msg))
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
