"""`monitor`, resolved through ament_index as `ros2 run` does, against real publishers."""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import numpy as np
import rclpy
from ament_index_python.packages import get_package_prefix
from executables import executable, finish

from co3sop_msgs.msg import VoxelScan
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.messages import scan_msg
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.v2x.scan import ScanCodecConfig, encode_scan


def test_executables_resolve_like_ros2_run():
    # ros2run lists <prefix>/lib/<package> and runs the executable file named there.
    lib = Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes")
    found = {p.name for p in lib.iterdir() if p.is_file() and os.access(p, os.X_OK)}
    assert {"monitor", "sample_stream"} <= found


def test_monitor_reports_rate_size_ratio_decode_time_and_grid(processes):
    monitor = processes.start(executable("monitor"), "--count", "24", "--duration", "90", "--period", "0.5")
    stream = processes.start(
        executable("sample_stream"),
        "--agents",
        "1",
        "2",
        "--frames",
        "20",
        "--rate",
        "20",
        "--dtype",
        "int8",
        "--ros-args",
        "-r",
        "__node:=sample_stream_test",
    )
    code, out = finish(monitor)
    assert code == 0, out
    assert finish(stream)[0] == 0
    last = {}
    for line in out.splitlines():  # the last report line per topic
        m = re.match(
            r"\[monitor\] (/\S+)\s+(\w+)\s+([\d.]+) Hz\s+n=(\d+)\s+wire\s+([\d.]+) "
            r"KB/msg\s+ratio\s+([\d.]+)x\s+decode\s+([\d.]+) ms\s+\| (.*)",
            line,
        )
        if m:
            last[m.group(1)] = m
    assert set(last) == {"/cav_1/voxel_features", "/cav_2/voxel_features", "/ego/occupancy"}, out
    features, occupancy = last["/cav_1/voxel_features"], last["/ego/occupancy"]
    assert features.group(2) == "VoxelFeatures" and occupancy.group(2) == "SemanticOccupancy"
    assert 5 < float(features.group(3)) < 40  # published at 20 Hz
    assert float(features.group(5)) > 100  # int8 64x64x6x64 features: ~1.5 MB raw
    assert float(occupancy.group(6)) > 10  # label grids compress well
    assert float(features.group(7)) > 0
    assert "grid 64x64x6 @0.800 m" in features.group(8) and "C=64 int8 zstd dense" in features.group(8)
    assert "frame cav_1/lidar agent 1" in features.group(8)
    assert "grid 256x256x24 @0.200 m" in occupancy.group(8) and "classes 24" in occupancy.group(8)


def test_monitor_counts_undecodable_payloads_and_keeps_going(processes):
    monitor = processes.start(
        executable("monitor"), "--topics", "/test_corrupt/voxel_features", "--count", "1", "--duration", "60"
    )
    processes.peer("corrupt.py")
    code, out = finish(monitor)
    assert code == 0, out
    assert "/test_corrupt/voxel_features" in out
    assert "errors 1 (last: values: truncated or corrupt zstd payload" in out, out
    assert "n=1" in out


def test_monitor_reports_voxel_scans(processes, peer):
    monitor = processes.start(executable("monitor"), "--count", "3", "--duration", "60", "--period", "0.5")
    grid = GridSpec((-25.6, -25.6, -2.0), 0.2, (256, 256, 24))
    occupancy = np.random.default_rng(0).random(grid.dims) < 0.005
    msg = scan_msg(
        RCLPY,
        encode_scan(occupancy, grid, ScanCodecConfig()),
        stamp_ns=10**18,
        frame_id="cav_5/lidar",
        agent_id=5,
        pose=Pose((0.0, 0.0, 1.8)),
    )
    pub = peer.create_publisher(VoxelScan, "/cav_5/voxel_scan", 10)
    deadline = time.monotonic() + 60
    while monitor.poll() is None and time.monotonic() < deadline:  # until the monitor has its count
        pub.publish(msg)
        rclpy.spin_once(peer, timeout_sec=0.3)
    code, out = finish(monitor)
    assert code == 0, out
    line = [x for x in out.splitlines() if x.startswith("[monitor] /cav_5/voxel_scan  VoxelScan")][-1]
    assert f"{int(occupancy.sum())} occupied zstd" in line and "grid 256x256x24 @0.200 m" in line, line
    assert "frame cav_5/lidar agent 5" in line
