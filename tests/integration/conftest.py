"""Integration tests: real processes over real DDS, resolved as `ros2 run` does."""

from __future__ import annotations

import os

import pytest
import rclpy
from executables import CALL_FAILED, Processes

from co3sop_nodes.ros.supervisor import Supervisor


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    """Whether the test itself failed, for fixtures that say more at teardown (`call_failed`)."""
    report = yield
    if report.when == "call":
        item.stash[CALL_FAILED] = report.failed
    return report


@pytest.fixture(scope="session", autouse=True)
def ros_domain():
    """One ROS_DOMAIN_ID per test process, so parallel runs never see each other: the workers of one run
    (pytest-xdist's gw0, gw1, ...) take consecutive ids after their controller's."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    session = os.getppid() if worker else os.getpid()
    os.environ["ROS_DOMAIN_ID"] = str(1 + (session + int(worker[2:] if worker else 0)) % 100)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    yield os.environ["ROS_DOMAIN_ID"]


@pytest.fixture
def processes():
    procs = Processes()
    yield procs
    procs.close()


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
