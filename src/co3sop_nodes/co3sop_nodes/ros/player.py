"""`player`: replay a rosbag2 bag (ours, or converted from OPV2V) onto its topics, with /clock.

    ros2 run co3sop_nodes player BAG [--rate 1.0] [--start 0.0] [--loop] [--topics T ...] [--read-ahead-queue-size N]

Messages go out raw (the bag's CDR bytes, never deserialised) at their
recorded times scaled by --rate, after skipping the first --start seconds,
read from the bag on a thread of their own up to --read-ahead-queue-size
messages ahead (data/playback.py), so a slow read never holds frames back;
/clock carries the bag time as the messages reach it (once per time: a frame's
messages share one), so nodes with use_sim_time follow the bag. Each topic
keeps the QoS it was recorded with (latched /tf_static stays latched). At the end of the bag the player exits, or starts
over with --loop (the clock then continues past the bag's end, so time never
runs backwards).
"""

from __future__ import annotations

import argparse
import sys
import time
from operator import itemgetter

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args
from rosgraph_msgs.msg import Clock

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.data.bags import open_reader
from co3sop_nodes.data.playback import ReadAhead, paced
from co3sop_nodes.messages import time_msg
from co3sop_nodes.ros.dds import flush_publishers, spin_node
from co3sop_nodes.ros.message_types import RCLPY, message_class


def recorded_qos(connection) -> QoSProfile:
    """The first QoS the topic was recorded with (reliable keep-last 10 if none)."""
    profiles = getattr(connection.ext, "offered_qos_profiles", None) or []
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
    if profiles:
        p = profiles[0]
        # rosbags gives its own enums (same numbers as rmw's)
        if int(getattr(p.durability, "value", p.durability)) == int(DurabilityPolicy.TRANSIENT_LOCAL):
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
            # keep every latched message of the bag (e.g. one /tf_static per CAV), not just the last
            qos.depth = max(1, p.depth, connection.msgcount)
        if int(getattr(p.reliability, "value", p.reliability)) == int(ReliabilityPolicy.BEST_EFFORT):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
    return qos


class Player(Node):
    def __init__(self, opts: argparse.Namespace):
        super().__init__("player")
        self._opts = opts
        self._reader = open_reader(opts.bag)
        self._reader.open()
        conns, self._pubs = [], {}
        for c in self._reader.connections:
            if opts.topics and c.topic not in opts.topics:
                continue
            try:
                self._pubs[c.id] = self.create_publisher(message_class(c.msgtype), c.topic, recorded_qos(c))
                conns.append(c)
            except DatasetError as exc:  # a type this environment lacks: play the rest
                self.get_logger().warning(f"{c.topic} not played: {exc}")
        if not conns:
            raise DatasetError(f"{opts.bag}: no topic to play (asked for: {opts.topics or 'all'})")
        self._conns = conns
        self._clock = self.create_publisher(Clock, topics.CLOCK, 10)
        self._start_ns = self._reader.start_time + int(opts.start * 1e9)
        self._duration_ns = self._reader.end_time - self._reader.start_time
        if self._start_ns >= self._reader.end_time:  # nothing to play (and, looping, nothing to wait for)
            self._reader.close()
            raise DatasetError(
                f"{opts.bag}: --start {opts.start:g} s is past its last message ({self._duration_ns / 1e9:.1f} s in)"
            )
        self._loops = 0
        self.published = 0

    def close(self) -> None:
        self._reader.close()

    def wait_for_subscribers(self, timeout: float) -> None:
        """Waits (at most `timeout` s) until every topic has a subscriber, so nothing is played to nobody."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and any(p.get_subscription_count() == 0 for p in self._pubs.values()):
            time.sleep(0.05)

    def play(self) -> None:
        """Publishes the bag (once, or forever with --loop) in real time scaled by --rate; /clock once per bag time
        (a frame's messages share theirs: one clock message, not one per message)."""
        opts = self._opts
        self.get_logger().info(
            f"playing {opts.bag}: {len(self._conns)} topics, {self._duration_ns / 1e9:.1f} s at rate {opts.rate}"
            + (" (looping)" if opts.loop else "")
        )
        clock = None
        while True:
            before = self.published
            messages = self._reader.messages(connections=self._conns, start=self._start_ns)
            with ReadAhead(messages, opts.read_ahead_queue_size) as ahead:
                ahead.fill()
                for conn, stamp, raw in paced(ahead, itemgetter(1), opts.rate, self._start_ns):
                    now = stamp + self._loops * (self._duration_ns + 1)  # the clock keeps going forward when looping
                    if now != clock:
                        self._clock.publish(Clock(clock=time_msg(RCLPY, now)))
                        clock = now
                    self._pubs[conn.id].publish(bytes(raw))
                    self.published += 1
            if not opts.loop:
                break
            if self.published == before:  # the topics played have nothing from --start on: looping would spin
                raise DatasetError(f"{opts.bag}: no message of the topics played at or after --start {opts.start:g} s")
            self._loops += 1
        flush_publishers(self, self._pubs.values())
        self.get_logger().info(f"end of bag: {self.published} messages published")


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="player", description=__doc__.split("\n\n")[1])
    parser.add_argument("bag", help="a rosbag2 bag folder (metadata.yaml + MCAP)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor")
    parser.add_argument("--start", type=float, default=0.0, help="seconds of the bag to skip")
    parser.add_argument("--loop", action="store_true", help="start over at the end, until stopped")
    parser.add_argument("--topics", nargs="*", default=[], help="only these topics (default: all)")
    parser.add_argument(
        "--read-ahead-queue-size",
        type=int,
        default=1000,
        help="messages read from the bag ahead of playing them (playing starts once that many are read)",
    )
    parser.add_argument(
        "--wait-subscribers",
        type=float,
        default=0.0,
        help="wait up to this many seconds for every topic to have a subscriber before playing",
    )
    argv = sys.argv if args is None else args
    opts = parser.parse_args(remove_ros_args(argv)[1:])
    if opts.rate <= 0:
        parser.error("--rate must be positive")
    if opts.start < 0:
        parser.error("--start must be at least 0 s")
    if opts.read_ahead_queue_size < 1:
        parser.error("--read-ahead-queue-size must be at least 1")

    def make() -> Node:
        player = Player(opts)
        try:
            player.wait_for_subscribers(opts.wait_subscribers)
            player.play()
        finally:
            player.close()
            # spin_node never holds this node (it is done before spinning): its DDS entities go now, before
            # the context shuts down, not in the interpreter's teardown
            player.destroy_node()
        raise SystemExit(0)

    return spin_node(make, argv, "player")


if __name__ == "__main__":
    sys.exit(main())
