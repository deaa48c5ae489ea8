"""`recorder`: writes predictions, ground truth and diagnostics to one MCAP file, never deserialising.

    ros2 run co3sop_nodes recorder --out results/demo/demo.mcap [--topics REGEX ...] [--flush-period 1.0]
        [--compression zstd|lz4|none]

Subscribes raw (the CDR bytes as they arrived) to every topic whose name
matches one of the patterns, as topics appear (default: /ego/occupancy, the
ground truth of every CAV, /diagnostics), and writes them to an MCAP file in
the ros2 profile with their schemas embedded (rosbags, `ros2 bag` and Foxglove
read it). The ego's prediction and its ground truth at the prediction's range
are also written as coloured points, on /ego/occupancy/points and
/ego/ground_truth/points (viz/recording_clouds.py), so a viewer draws them
side by side; the recorder draws them from the label grids rather than
recording the ego's own cloud, which the ego then only makes for a live
viewer. Chunks are flushed as they fill and at least every --flush-period s;
SIGINT or SIGTERM finalises the file. After a crash, at
most the last chunk is lost and `recover` makes the file readable again.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.data.recording import COMPRESSIONS, McapRecorder
from co3sop_nodes.kernels import visible_voxels
from co3sop_nodes.messages.sensors import POINT_CLOUD
from co3sop_nodes.ros.dds import DropLog, matching_qos, spin_node
from co3sop_nodes.ros.message_types import message_class
from co3sop_nodes.viz.recording_clouds import RecordingClouds, is_drawn

DEFAULT_TOPICS = (
    re.escape(topics.EGO_OCCUPANCY),
    r"/cav_\d+/ground_truth/occupancy_\w+",
    re.escape(topics.DIAGNOSTICS),
)
# Deep queues: the recorder must keep up with bursts rather than lose messages.
RECORD_DEPTH = 200


class Recorder(Node):
    def __init__(self, opts: argparse.Namespace):
        super().__init__("recorder")
        self._patterns = [re.compile(f"^{t}$") for t in opts.topics]
        self._types: dict[str, str] = {}
        self._subs = []
        self.mcap = McapRecorder(opts.out, chunk_size=opts.chunk_size, compression=opts.compression)
        self.clouds = RecordingClouds()
        visible_voxels.available()  # its kernel compiled now, not while the first ground truth waits
        self.drops = DropLog(self.get_logger())
        self.create_timer(0.2, self._discover)
        self.create_timer(opts.flush_period, self.mcap.flush)
        self._discover()
        self.get_logger().info(f"recording to {opts.out}: topics matching {', '.join(opts.topics)}")

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._types or is_drawn(topic) or not any(p.match(topic) for p in self._patterns):
                continue
            qos = matching_qos(self, topic, RECORD_DEPTH)  # each publisher's QoS adopted, as ros2 bag record does
            if qos is None:  # only subscribers so far
                continue
            self._types[topic] = types[0]
            try:
                cls = message_class(types[0])
            except Co3sopError as exc:
                self.get_logger().warning(f"{topic} not recorded: {exc}")
                continue
            self._subs.append(
                self.create_subscription(cls, topic, lambda raw, t=topic: self._on_message(t, raw), qos, raw=True)
            )
            self.get_logger().info(f"recording {topic} ({types[0]}, {qos.reliability.name.lower()})")

    def _on_message(self, topic: str, raw: bytes) -> None:
        now = time.time_ns()
        self.mcap.write(topic, self._types[topic], raw, now)
        try:
            clouds = (
                self.clouds.prediction(raw, topic) if topics.is_ego_occupancy(topic) else self.clouds.truth(topic, raw)
            )
        except Co3sopError as exc:  # recorded as it came; only its picture is missing
            return self.drops(topic, "not drawn", str(exc))
        for shown, cloud in clouds:
            self.mcap.write(shown, POINT_CLOUD, cloud, now)

    def close(self) -> None:
        self.mcap.close()
        counts = ", ".join(f"{t} {n}" for t, n in sorted(self.mcap.counts.items())) or "nothing"
        # after rclpy shut down: plain output
        print(
            f"[recorder] finalised {self.mcap.path}: {sum(self.mcap.counts.values())} messages ({counts})", flush=True
        )


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="recorder", description=__doc__.split("\n\n")[1])
    parser.add_argument("--out", type=Path, required=True, help="the MCAP file to write")
    parser.add_argument("--topics", nargs="+", default=list(DEFAULT_TOPICS), help="regular expressions of topic names")
    parser.add_argument(
        "--chunk-size", type=int, default=256 * 1024, help="bytes per MCAP chunk (what a crash may lose)"
    )
    parser.add_argument(
        "--flush-period", type=float, default=1.0, help="seconds between flushes of a partly filled chunk"
    )
    parser.add_argument(
        "--compression",
        choices=list(COMPRESSIONS),
        default="zstd",
        help="chunk compression: zstd (smallest), lz4 (about half zstd's CPU, 2.5x the bytes), none",
    )
    argv = sys.argv if args is None else args
    opts = parser.parse_args(remove_ros_args(argv)[1:])
    if opts.chunk_size < 1 or not opts.flush_period > 0:
        parser.error("--chunk-size must be at least 1 byte, --flush-period above 0 s")
    for topic in opts.topics:
        try:
            re.compile(topic)
        except re.error as exc:
            parser.error(f"--topics {topic!r}: not a regular expression ({exc})")
    recorder = None

    def make() -> Node:
        nonlocal recorder
        recorder = Recorder(opts)
        return recorder

    try:
        return spin_node(make, argv, "recorder", events=True)
    finally:
        if recorder is not None:
            recorder.close()


if __name__ == "__main__":
    sys.exit(main())
