"""`player` replays a bag over real DDS: another process receives every message, /clock follows the bag."""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

import pytest
import rclpy
from executables import executable, finish
from rosgraph_msgs.msg import Clock

from co3sop_msgs.msg import SemanticOccupancy

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "opv2v"


TOPICS = ["/cav_4805/ground_truth/occupancy_50m", "/cav_4814/ground_truth/occupancy_50m"]


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("converted")
    converted = subprocess.run(
        [executable("convert"), str(FIXTURE), "--out", str(out)], capture_output=True, text=True, timeout=300
    )
    assert converted.returncode == 0, converted.stderr
    return out / "test" / "2021_08_24_21_29_28"


def test_player_replays_ground_truth_to_monitor(processes, bag):
    topics = TOPICS
    monitor = processes.start(
        executable("monitor"), "--topics", *topics, "--count", "4", "--duration", "60", "--period", "0.2"
    )
    player = processes.start(
        executable("player"), str(bag), "--rate", "2", "--topics", *topics, "--wait-subscribers", "20"
    )
    code, out = finish(monitor)
    assert code == 0, out
    code, played = finish(player)
    assert code == 0, played
    assert "end of bag: 4 messages published" in played  # 2 CAVs x 2 frames
    for topic in topics:
        lines = [line for line in out.splitlines() if line.startswith(f"[monitor] {topic} ")]
        assert lines and "grid 256x256x24 @0.200 m" in lines[-1] and "frame cav_" in lines[-1], out
        assert re.search(r"n=2\b", lines[-1]), lines[-1]


@pytest.mark.parametrize("read_ahead", ["1000", "1"])
def test_the_clock_goes_out_once_per_bag_time_and_forward(processes, peer, bag, read_ahead):
    """A frame's messages share their bag time: one /clock message for them, not one per message; whatever the
    read-ahead queue holds (one message: the reader waits for room before each), every message is played."""
    clocks, received = [], []
    peer.create_subscription(Clock, "/clock", lambda m: clocks.append(m.clock.sec * 10**9 + m.clock.nanosec), 100)
    for topic in TOPICS:  # the player waits for these subscriptions, made after the clock's
        peer.create_subscription(SemanticOccupancy, topic, received.append, 10)
    player = processes.start(
        executable("player"),
        str(bag),
        "--topics",
        *TOPICS,
        "--wait-subscribers",
        "20",
        "--read-ahead-queue-size",
        read_ahead,
    )
    deadline = time.monotonic() + 60
    while (player.poll() is None or len(received) < 4) and time.monotonic() < deadline:
        rclpy.spin_once(peer, timeout_sec=0.05)
    code, played = finish(player)
    assert code == 0 and len(received) == 4, played  # 2 CAVs x 2 frames
    assert clocks and clocks == sorted(set(clocks)) and len(clocks) <= 2, clocks  # the bag's 2 frames


def test_player_explains_a_missing_bag(tmp_path):
    result = subprocess.run(
        [executable("player"), str(tmp_path / "nothing")], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2 and "not a rosbag2 bag" in result.stderr and "Traceback" not in result.stderr


def test_player_refuses_an_empty_read_ahead_queue(bag):
    result = subprocess.run(
        [executable("player"), str(bag), "--read-ahead-queue-size", "0"], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2 and "--read-ahead-queue-size" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize(
    ("start", "topics", "error"),
    [
        ("60", [], "is past its last message"),
        ("-1", [], "--start must be at least 0"),
        # the mounts are latched at the bag's start: from its second frame on, nothing of that topic is left
        ("0.05", ["--topics", "/tf_static"], "no message of the topics played at or after --start 0.05 s"),
    ],
)
def test_player_explains_a_start_outside_the_bag(bag, start, topics, error):
    """A start past what is played plays nothing (with --loop, forever): refused, as a negative one is."""
    result = subprocess.run(
        [executable("player"), str(bag), "--start", start, "--loop", *topics],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and error in result.stderr and "Traceback" not in result.stderr, result.stderr
