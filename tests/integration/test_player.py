"""`player` replays a bag over real DDS: another process receives every message, /clock follows the bag."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from executables import executable, finish

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "opv2v"


def test_player_replays_ground_truth_to_monitor(processes, tmp_path):
    converted = subprocess.run(
        [executable("convert"), str(FIXTURE), "--out", str(tmp_path)], capture_output=True, text=True, timeout=300
    )
    assert converted.returncode == 0, converted.stderr
    bag = tmp_path / "test" / "2021_08_24_21_29_28"
    topics = ["/cav_4805/ground_truth/occupancy_50m", "/cav_4814/ground_truth/occupancy_50m"]
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


def test_player_explains_a_missing_bag(tmp_path):
    result = subprocess.run(
        [executable("player"), str(tmp_path / "nothing")], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2 and "not a rosbag2 bag" in result.stderr and "Traceback" not in result.stderr
