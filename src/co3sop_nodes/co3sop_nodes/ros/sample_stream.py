"""`sample_stream`: publish seeded synthetic features and occupancy for a while.

A traffic source for checking a DDS set-up end to end before any bag or model
is there (pair it with `monitor`): every --rate Hz, for each agent id, a
street-shaped feature volume with confidence on /cav_<id>/voxel_features, and
a street label grid on /ego/occupancy, encoded with the chosen codec settings.

    ros2 run co3sop_nodes sample_stream [--agents 1 2] [--rate 10] [--frames 30] [--dtype float16] ...
"""

from __future__ import annotations

import argparse
import sys
import time

from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from co3sop_msgs.msg import SemanticOccupancy, VoxelFeatures
from co3sop_nodes.common import topics
from co3sop_nodes.common.classes import NUM_CLASSES
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.data import synthetic
from co3sop_nodes.messages import features_msg, occupancy_msg
from co3sop_nodes.ros.dds import FEATURES_QOS, OCCUPANCY_QOS, flush_publishers, spin_node
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.v2x.codec import (
    CODECS,
    FEATURE_DTYPES,
    SELECTIONS,
    FeatureCodecConfig,
    encode_features,
    encode_labels,
)


class SampleStream(Node):
    def __init__(self, opts: argparse.Namespace):
        super().__init__("sample_stream")
        self._opts = opts
        self._cfg = FeatureCodecConfig(dtype=opts.dtype, selection=opts.selection, topk=opts.topk, codec=opts.codec)
        label_grid = BENCHMARK_RANGES[opts.range]
        # Feature volumes are at 1/4 of the label resolution, as in Co3SOP-Base.
        nx, ny, nz = label_grid.dims
        self._feature_grid = GridSpec(label_grid.origin, label_grid.voxel_size * 4, (nx // 4, ny // 4, nz // 4))
        self._label_grid = label_grid
        self._features = {
            a: self.create_publisher(VoxelFeatures, topics.voxel_features(a), FEATURES_QOS) for a in opts.agents
        }
        self._occupancy = self.create_publisher(SemanticOccupancy, topics.EGO_OCCUPANCY, OCCUPANCY_QOS)
        # Synthetic content is costly to make: a few seeded frames, cycled.
        self._frames = [
            (
                synthetic.feature_volume(self._feature_grid, opts.channels, seed),
                synthetic.street_labels(label_grid, seed),
            )
            for seed in range(min(opts.frames, 4))
        ]
        self._sent = 0
        self._wait_until = time.monotonic() + opts.wait_subscribers
        self.create_timer(1.0 / opts.rate, self._tick)
        print(
            f"[sample_stream] agents {opts.agents}: {opts.frames} frames at {opts.rate} Hz, features "
            f"{self._cfg.name} C={opts.channels} on a {'x'.join(map(str, self._feature_grid.dims))} grid, "
            f"labels {'x'.join(map(str, label_grid.dims))} ({opts.range})",
            flush=True,
        )

    def _tick(self) -> None:
        pubs = [*self._features.values(), self._occupancy]
        if self._sent >= self._opts.frames:
            flush_publishers(self, pubs)
            raise SystemExit(0)
        if time.monotonic() < self._wait_until and any(p.get_subscription_count() == 0 for p in pubs):
            return  # nobody listens yet: frames sent now would be lost
        (features, confidence), labels = self._frames[self._sent % len(self._frames)]
        stamp_ns = self.get_clock().now().nanoseconds
        for agent in self._opts.agents:
            enc = encode_features(features, confidence, self._feature_grid, self._cfg)
            pose = Pose((10.0 * agent, 0.0, 1.9))
            self._features[agent].publish(
                features_msg(RCLPY, enc, stamp_ns=stamp_ns, frame_id=f"cav_{agent}/lidar", agent_id=agent, pose=pose)
            )
        ego = self._opts.agents[0]
        enc = encode_labels(labels, self._label_grid, NUM_CLASSES, codec=self._opts.codec)
        self._occupancy.publish(occupancy_msg(RCLPY, enc, stamp_ns=stamp_ns, frame_id=f"cav_{ego}/lidar", agent_id=ego))
        self._sent += 1


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="sample_stream", description=__doc__.split("\n\n")[1])
    parser.add_argument("--agents", type=int, nargs="+", default=[1, 2], help="vehicle ids to publish features for")
    parser.add_argument("--rate", type=float, default=10.0, help="frames per second")
    parser.add_argument("--frames", type=int, default=30, help="frames to publish before exiting")
    parser.add_argument(
        "--range", choices=sorted(BENCHMARK_RANGES), default="51.2m", help="benchmark grid of the labels"
    )
    parser.add_argument("--channels", type=int, default=64, help="feature channels")
    parser.add_argument("--dtype", choices=sorted(FEATURE_DTYPES), default="float16")
    parser.add_argument("--selection", choices=SELECTIONS, default="dense")
    parser.add_argument("--topk", type=int, default=4096)
    parser.add_argument("--codec", choices=CODECS, default=FeatureCodecConfig.codec)
    parser.add_argument(
        "--wait-subscribers",
        type=float,
        default=0.0,
        help="hold the first frame up to this many seconds until every topic has a subscriber",
    )
    argv = sys.argv if args is None else args
    opts = parser.parse_args(remove_ros_args(argv)[1:])
    for name, value, low in (
        ("rate", opts.rate, 0.0),
        ("frames", opts.frames, 0),
        ("channels", opts.channels, 0),
        ("topk", opts.topk, 0),
    ):
        if not value > low:
            parser.error(f"--{name} {value}: must be above {low}")
    if opts.wait_subscribers < 0:
        parser.error(f"--wait-subscribers {opts.wait_subscribers}: must be 0 or more")
    return spin_node(lambda: SampleStream(opts), argv, "sample_stream")


if __name__ == "__main__":
    sys.exit(main())
