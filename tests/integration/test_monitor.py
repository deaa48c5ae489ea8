"""`monitor`, resolved through ament_index as `ros2 run` does, against real publishers."""

from __future__ import annotations

import os
import re
from pathlib import Path

from ament_index_python.packages import get_package_prefix
from conftest import executable, finish


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
