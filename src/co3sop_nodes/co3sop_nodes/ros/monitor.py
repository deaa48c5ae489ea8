"""`monitor`: watch the project's topics and report what crosses the wire.

Subscribes (raw, so it sees the exact serialized size) to every
co3sop_msgs/VoxelFeatures, VoxelScan and SemanticOccupancy topic it discovers,
or to the topics named, and prints per topic: message rate, bytes on the wire
per message, compression ratio (uncompressed payload / compressed payload),
decode time (deserialize + decompress + unpack), and the last decoded
header and grid. Payloads that fail to decode are counted and reported with
the reason; they never stop the monitor.

    ros2 run co3sop_nodes monitor [--topics T ...] [--period S] [--count N] [--duration S]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import numpy as np
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from rclpy.utilities import remove_ros_args

from co3sop_msgs.msg import SemanticOccupancy, VoxelFeatures, VoxelScan
from co3sop_nodes.common.classes import CLASS_NAMES
from co3sop_nodes.common.errors import Co3sopError, exception_line
from co3sop_nodes.messages import features_of, occupancy_of, scan_of, stamp_ns
from co3sop_nodes.ros.dds import OCCUPANCY_QOS, spin_node
from co3sop_nodes.v2x.codec import decode_features, decode_labels
from co3sop_nodes.v2x.scan import decode_scan

MONITORED = {
    "co3sop_msgs/msg/VoxelFeatures": VoxelFeatures,
    "co3sop_msgs/msg/VoxelScan": VoxelScan,
    "co3sop_msgs/msg/SemanticOccupancy": SemanticOccupancy,
}


@dataclass
class TopicStats:
    type_name: str
    count: int = 0
    errors: int = 0
    wire_bytes: int = 0
    raw_bytes: int = 0
    payload_bytes: int = 0
    decode_s: float = 0.0
    first_t: float = 0.0
    last_t: float = 0.0
    last: str = ""
    last_error: str = ""

    def line(self, topic: str) -> str:
        if not self.count:
            return f"{topic}  {self.type_name}  no message decoded yet (errors {self.errors}: {self.last_error})"
        rate = (self.count - 1) / (self.last_t - self.first_t) if self.count > 1 and self.last_t > self.first_t else 0.0
        ratio = self.raw_bytes / self.payload_bytes if self.payload_bytes else float("inf")
        text = (
            f"{topic}  {self.type_name}  {rate:6.2f} Hz  n={self.count}  "
            f"wire {self.wire_bytes / self.count / 1024:9.1f} KB/msg  ratio {ratio:6.2f}x  "
            f"decode {self.decode_s / self.count * 1e3:7.2f} ms  | {self.last}"
        )
        if self.errors:
            text += f"  | errors {self.errors} (last: {self.last_error})"
        return text


def _grid_text(grid) -> str:
    nx, ny, nz = grid.dims
    ox, oy, oz = grid.origin
    return f"grid {nx}x{ny}x{nz} @{grid.voxel_size:.3f} m origin ({ox:.2f}, {oy:.2f}, {oz:.2f})"


def _header_text(header, agent_id: int) -> str:
    return f"stamp {stamp_ns(header.stamp) / 1e9:.3f} frame {header.frame_id} agent {agent_id}"


def summarize_features(msg: VoxelFeatures) -> tuple[str, int, int]:
    """Decodes one message; returns (summary, raw payload bytes, compressed payload bytes)."""
    enc = features_of(msg)
    dec = decode_features(enc)
    layout = f"sparse N={enc.num_voxels}" if enc.sparse else "dense"
    conf = "" if dec.confidence is None else f" conf mean {dec.confidence.mean():.3f}"
    text = (
        f"{_header_text(msg.header, msg.agent_id)}  {_grid_text(enc.grid)}  "
        f"C={enc.channels} {enc.dtype} {enc.codec} {layout}{conf}"
        + (f" learned code {enc.learned_code}" if enc.learned_code else "")
    )
    return text, enc.raw_bytes, enc.payload_bytes


def summarize_scan(msg: VoxelScan) -> tuple[str, int, int]:
    enc = scan_of(msg)
    decode_scan(enc)
    text = f"{_header_text(msg.header, msg.agent_id)}  {_grid_text(enc.grid)}  {enc.num_voxels} occupied {enc.codec}"
    return text, enc.occupancy_raw_size, enc.payload_bytes


def summarize_occupancy(msg: SemanticOccupancy) -> tuple[str, int, int]:
    enc = occupancy_of(msg)
    dec = decode_labels(enc)
    counts = np.bincount(dec.labels.reshape(-1), minlength=256)
    top = [int(c) for c in np.argsort(-counts)[:3] if counts[c]]
    names = ", ".join(f"{CLASS_NAMES[c] if c < len(CLASS_NAMES) else c} {counts[c] / dec.labels.size:.1%}" for c in top)
    text = f"{_header_text(msg.header, msg.agent_id)}  {_grid_text(enc.grid)}  classes {enc.num_classes} {enc.codec}  [{names}]"
    return text, enc.raw_bytes, enc.payload_bytes


SUMMARIZERS = {VoxelFeatures: summarize_features, VoxelScan: summarize_scan, SemanticOccupancy: summarize_occupancy}


class Monitor(Node):
    def __init__(self, topics: list[str], period: float, count: int, duration: float):
        super().__init__("monitor")
        self._named = topics
        self._count = count
        self._deadline = time.monotonic() + duration if duration > 0 else None
        self._stats: dict[str, TopicStats] = {}
        self._subs = {}
        self._discover()
        self.create_timer(0.5, self._discover)
        self.create_timer(period, self._report)

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or (self._named and topic not in self._named):
                continue
            known = [t for t in types if t in MONITORED]
            if not known:
                if self._named:
                    self.get_logger().warning(f"{topic} has type {types}, not a Co3SOP payload type: not monitored")
                    self._subs[topic] = None
                continue
            msg_type = MONITORED[known[0]]
            self._stats[topic] = TopicStats(known[0].rsplit("/", 1)[-1])
            self._subs[topic] = self.create_subscription(
                msg_type, topic, lambda raw, t=topic, m=msg_type: self._on_message(t, m, raw), OCCUPANCY_QOS, raw=True
            )
            print(f"[monitor] subscribed to {topic} ({known[0]})", flush=True)

    def _on_message(self, topic: str, msg_type, raw: bytes) -> None:
        stats = self._stats[topic]
        now = time.monotonic()
        t0 = time.perf_counter()
        try:
            msg = deserialize_message(raw, msg_type)
        except Exception as exc:
            return self._error(
                topic, stats, f"{len(raw)} bytes that are not a valid {msg_type.__name__} ({exception_line(exc)})"
            )
        try:
            text, raw_size, payload = SUMMARIZERS[msg_type](msg)
        except Co3sopError as exc:
            return self._error(topic, stats, str(exc))
        stats.decode_s += time.perf_counter() - t0
        if not stats.count:
            stats.first_t = now
        stats.count += 1
        stats.last_t = now
        stats.wire_bytes += len(raw)
        stats.raw_bytes += raw_size
        stats.payload_bytes += payload
        stats.last = text
        if self._count and sum(s.count for s in self._stats.values()) >= self._count:
            self._report()
            raise SystemExit(0)

    def _error(self, topic: str, stats: TopicStats, reason: str) -> None:
        stats.errors += 1
        stats.last_error = reason
        self.get_logger().warning(f"{topic}: dropped a message that does not decode: {reason}")

    def _report(self) -> None:
        if self._deadline is not None and time.monotonic() > self._deadline:
            self._print()
            if self._count:
                print(f"[monitor] error: fewer than {self._count} messages before --duration ran out", file=sys.stderr)
                raise SystemExit(1)
            raise SystemExit(0)
        self._print()

    def _print(self) -> None:
        if not self._stats:
            print("[monitor] waiting for VoxelFeatures / VoxelScan / SemanticOccupancy topics...", flush=True)
        for topic in sorted(self._stats):
            print("[monitor] " + self._stats[topic].line(topic), flush=True)


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="monitor", description=__doc__.split("\n\n")[1])
    parser.add_argument(
        "--topics", nargs="*", default=[], help="topics to watch (default: every payload topic discovered)"
    )
    parser.add_argument("--period", type=float, default=1.0, help="seconds between reports")
    parser.add_argument("--count", type=int, default=0, help="exit after this many decoded messages in all (0: never)")
    parser.add_argument("--duration", type=float, default=0.0, help="exit after this many seconds (0: never)")
    argv = sys.argv if args is None else args
    opts = parser.parse_args(remove_ros_args(argv)[1:])
    if not opts.period > 0 or opts.count < 0 or opts.duration < 0:
        parser.error("--period must be above 0, --count and --duration 0 or more")
    return spin_node(lambda: Monitor(opts.topics, opts.period, opts.count, opts.duration), argv, "monitor")


if __name__ == "__main__":
    sys.exit(main())
