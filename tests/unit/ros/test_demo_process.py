"""The demo's child processes: the CPU each one uses, read while it runs."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from co3sop_nodes.ros.demo import Process
from co3sop_nodes.ros.graph import describe

# 0.3 s of CPU, then idle until stopped; it takes SIGINT as a node does (rclpy installs its own handler), also when
# the suite runs in the background, whose children inherit SIGINT ignored
BURN = (
    "import signal, time\nsignal.signal(signal.SIGINT, signal.default_int_handler)\n"
    "t = time.process_time()\nwhile time.process_time() - t < 0.3: pass\ntime.sleep(60)\n"
)


def test_cpu_seconds_counts_what_a_running_child_used_and_none_once_it_ended():
    child = Process("burner", [sys.executable, "-c", BURN], echo=False)
    try:
        deadline = time.monotonic() + 20
        while child.cpu_seconds() < 0.3 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)  # idle now: its count stays
        assert 0.3 <= child.cpu_seconds() < 0.3 + 2  # its 0.3 s of work and the interpreter's start, not its sleep
    finally:
        child.stop()
    assert child.cpu_seconds() is None


def test_a_prefixed_child_runs_at_its_niceness_and_is_measured_as_itself(tmp_path):
    recorder = describe(tmp_path / "bag", [3, 5], "lidar", tmp_path / "g.mcap", 1.0).recorder
    assert recorder.niceness > 0
    child = Process("nice", [*recorder.prefix, sys.executable, "-c", BURN], echo=False)
    try:
        deadline = time.monotonic() + 20
        while child.cpu_seconds() < 0.3 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert child.cpu_seconds() >= 0.3  # `nice` became the command, in the process the demo measures
        stat = Path(f"/proc/{child.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        assert int(stat[16]) == recorder.niceness  # nice, the 19th field (the 17th after "pid (name)")
    finally:
        child.stop()
