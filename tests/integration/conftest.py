"""Integration tests: real processes over real DDS, resolved as `ros2 run` does."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import rclpy
from ament_index_python.packages import get_package_prefix

from co3sop_nodes.ros.supervisor import Supervisor

HERE = Path(__file__).resolve().parent


@pytest.fixture(scope="session", autouse=True)
def ros_domain():
    """One ROS_DOMAIN_ID per test session, so parallel runs never see each other."""
    os.environ["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 100)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    yield os.environ["ROS_DOMAIN_ID"]


def executable(name: str) -> str:
    """Path of a co3sop_nodes executable, found exactly as ros2run finds it."""
    path = Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes", name)
    assert path.is_file() and os.access(path, os.X_OK), f"{path} is not an installed executable"
    return str(path)


class Processes:
    """Started processes; whatever is still running at teardown is interrupted, then killed."""

    def __init__(self):
        self._procs: list[subprocess.Popen] = []

    def start(self, *argv: str) -> subprocess.Popen:
        proc = subprocess.Popen(
            list(argv), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=dict(os.environ)
        )
        self._procs.append(proc)
        return proc

    def peer(self, *args: str) -> subprocess.Popen:
        """A test peer script from tests/integration/peers, run by this interpreter."""
        return self.start(sys.executable, str(HERE / "peers" / args[0]), *args[1:])

    def close(self) -> None:
        for proc in self._procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in self._procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture
def processes():
    procs = Processes()
    yield procs
    procs.close()


def finish(proc: subprocess.Popen, timeout: float = 120) -> tuple[int, str]:
    """Waits for a process; returns (exit code, its combined output)."""
    out, _ = proc.communicate(timeout=timeout)
    return proc.returncode, out


@pytest.fixture
def peer():
    """This test process as a DDS participant."""
    rclpy.init()
    node = rclpy.create_node("test_peer")
    yield node
    node.destroy_node()
    rclpy.try_shutdown()


@pytest.fixture
def sup():
    """A supervisor: lifecycle states, /diagnostics reports, the graph."""
    with Supervisor("fault_test") as supervisor:
        yield supervisor
