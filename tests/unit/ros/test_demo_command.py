"""`demo`'s channel options are checked before anything starts (parsing only: no node, no namespace)."""

from __future__ import annotations

import os
import sys
import xml.etree.ElementTree as ET

import pytest

from co3sop_nodes.cli.demo import main

NS = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--channel-answer-ms", "5"], "need --channel-rate"),
        (["--channel-shared"], "need --channel-rate"),
        (["--channel-rate", "6", "--channel-answer-ms", "-1"], "--channel-answer-ms -1.0: 0 to 10000"),
        (["--channel-rate", "6", "--channel-shared", "--channel-maps-first"], "--channel-maps-first needs"),
    ],
)
def test_channel_options_are_refused_by_name(argv, message, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_only_what_crosses_the_radio_is_slowed_with_the_play_rate(tmp_path, monkeypatch):
    """Every CAV an ego at rate 0.1: the vehicles' features and the request maps run Fast DDS's timers 10 times slower
    (the default profiles); the sensors the simulator plays (whose last messages must be repaired before the player
    exits), /clock, each ego's features on board, its outputs and /diagnostics keep Fast DDS's own."""
    from co3sop_nodes.ros import demo
    from co3sop_nodes.ros.dds import CHANNEL_PROFILES, WRITER_TIMES

    for name in ("FASTRTPS_DEFAULT_PROFILES_FILE", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(name, "")  # restored after the test: _open_channel sets this process's DDS environment
    monkeypatch.setattr(demo, "bag_period", lambda bag, frames: 0.1)
    opts = demo.DemoOptions(out=tmp_path, rate=0.1, channel_rate=12.0, channel_shared=True, egos="all")
    _, profiles = demo._open_channel(opts, tmp_path / "bag", 5, [3, 7], [3, 7], "lidar")
    root = ET.parse(profiles / CHANNEL_PROFILES[1]).getroot()
    period = {
        w.get("profile_name"): int(w.find("p:times/p:heartbeatPeriod/p:sec", NS).text)
        for w in root.findall("p:profiles/p:data_writer", NS)
    }
    assert period.pop("v2x_default") == 10 * WRITER_TIMES["heartbeatPeriod"]
    own = {"/tf_static", "/clock", "/diagnostics", "/cav_3/lidar/points", "/cav_7/lidar/pose", "/cav_3/ego/occupancy"}
    own |= {"/cav_7/voxel_features/local", "/cav_3/ground_truth/occupancy_50m", "/cav_7/ego/ground_truth/points"}
    assert own <= set(period) and set(period.values()) == {WRITER_TIMES["heartbeatPeriod"]}
    assert not {"/cav_3/voxel_features", "/cav_7/ego/request_map"} & set(period)  # on the radio
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(profiles / CHANNEL_PROFILES[0])


def test_a_quiet_childs_last_warnings_explain_a_failure(capsys):
    from co3sop_nodes.ros.demo import Process, warned

    code = "for i in range(5): print(f'[WARN] [0.0] [player]: lost {i}'); print('[INFO] fine')"
    child = Process("player", [sys.executable, "-c", code], echo=False)
    assert child.proc.wait(30) == 0 and child.stop() == 0 and capsys.readouterr().out == ""  # swallowed
    assert warned(child, None) == "; their last warnings:\n  " + "\n  ".join(
        f"[player] [WARN] [0.0] [player]: lost {i}" for i in (2, 3, 4)
    )
    quiet = Process("quiet", [sys.executable, "-c", "print('[INFO] fine')"], echo=False)
    assert quiet.proc.wait(30) == 0 and quiet.stop() == 0 and warned(quiet) == ""


def test_the_bag_waits_for_the_shared_medium_to_fall_quiet():
    """The nodes' start-up traffic still crossing a slowed medium would delay the first frames' messages: the demo
    plays once the medium carried under a tenth of its rate for 2 s."""
    from co3sop_nodes.ros.demo import QuietMedium
    from co3sop_nodes.v2x.channel import Link

    class Medium:  # what Channel reports of its shared medium
        shared = Link(0.8)  # 100 KB/s
        carried = 0

        def carried_by_medium(self) -> int:
            return self.carried

    medium, now = Medium(), [0.0]
    quiet = QuietMedium(medium, clock=lambda: now[0])
    busy = []
    for step in range(40):  # 10 s: 60 KB/s for 5 s (start-up), then 5 KB/s (heartbeats)
        now[0] = step * 0.25
        medium.carried += 15_000 if now[0] < 5 else 1_250
        busy.append(quiet())
    assert not any(busy[:27]) and all(busy[27:])  # quiet once the last 2 s hold no burst
