"""The package's installed executables, found exactly as `ros2 run` finds them, and the processes a test starts.
Test modules import these from here, not from conftest.py: under `colcon test` the unit tests' conftest.py is
imported first, and a bare `import conftest` would find that one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from ament_index_python.packages import get_package_prefix

HERE = Path(__file__).resolve().parent
CALL_FAILED = pytest.StashKey[bool]()  # set by conftest.py's report hook


def call_failed(request: pytest.FixtureRequest) -> bool:
    """In a fixture's teardown: whether its test failed (to say more about it, e.g. the nodes' logs)."""
    return request.node.stash.get(CALL_FAILED, False)


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


def exit_code(proc: subprocess.Popen, log: Path, timeout: float = 30) -> int:
    """A stopped node's exit code, once it has exited. One still running after `timeout` s fails the test with its
    log (its output), which then ends with every thread's stack: it is aborted, and its faulthandler prints them."""
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        pytest.fail(f"{' '.join(map(str, proc.args))} still ran {timeout:g} s after it was stopped:\n{log.read_text()}")


def finish(proc: subprocess.Popen, timeout: float = 120) -> tuple[int, str]:
    """Waits for a process; returns (exit code, its combined output). One still running after `timeout` s fails the
    test with its output, which ends with every thread's stack: it is aborted, and a node's faulthandler prints them
    as it dies (a hang otherwise says nothing of where)."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        try:
            out, _ = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        pytest.fail(f"{' '.join(map(str, proc.args))} still ran after {timeout:g} s; its output:\n{out}")
    return proc.returncode, out
