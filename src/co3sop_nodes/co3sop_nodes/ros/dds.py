"""DDS settings every Co3SOP process applies, QoS profiles, and the node main loop."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable

import rclpy
from ament_index_python.packages import get_package_share_directory
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..errors import Co3sopError

PACKAGE = "co3sop_nodes"

# Features and predictions are large multi-fragment samples: best effort would
# drop whole samples, so reliable with a short queue (a late frame is useless).
FEATURES_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=2,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
OCCUPANCY_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=5,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
# /diagnostics: one status per node per frame; reliable so the recorder and benchmarks see every one
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)


def flush_publishers(node: Node, publishers, timeout: float = 5.0) -> None:
    """Waits (at most `timeout` s in all) until reliable subscribers acknowledged everything published:
    a node that exits right after its last publish would otherwise take those messages down with it."""
    deadline = time.monotonic() + timeout
    for pub in publishers:
        if not pub.wait_for_all_acked(Duration(seconds=max(0.0, deadline - time.monotonic()))):
            node.get_logger().warning(f"{pub.topic_name}: not every subscriber acknowledged the last messages")


def fastdds_profile_path() -> str:
    """The shipped Fast DDS profile (large shared-memory segment)."""
    return os.path.join(get_package_share_directory(PACKAGE), "config", "fastdds.xml")


def configure_environment() -> None:
    """Project defaults, applied before rclpy.init(); variables already set win.

    Discovery stays on this host unless ROS_AUTOMATIC_DISCOVERY_RANGE says
    otherwise (SUBNET for several hosts); every participant uses the shipped
    Fast DDS profile unless FASTRTPS_DEFAULT_PROFILES_FILE names another.
    """
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", fastdds_profile_path())


def spin_node(make_node: Callable[[], Node], args: list[str] | None = None, prog: str = "") -> int:
    """The Jazzy node idiom: init, spin until Ctrl-C or shutdown, always clean up.

    `make_node` may raise SystemExit (e.g. a node that finished its job); its
    code is returned. Bad input (Co3sopError) or a file problem (OSError)
    prints `<prog>: error: <message>` and returns 2, never a traceback.
    """
    try:
        return _spin(make_node, args)
    except (Co3sopError, OSError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2


def _spin(make_node: Callable[[], Node], args: list[str] | None) -> int:
    configure_environment()
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = make_node()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemExit as done:
        code = int(done.code or 0)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code
