"""The integration tests' own harness: a process that hangs fails its test with where it hung."""

import sys

import pytest
from executables import Processes, finish

HANG = """import faulthandler, time
faulthandler.enable(all_threads=True)
def stuck_here():
    time.sleep(60)
stuck_here()
"""


def test_a_process_still_running_at_its_timeout_fails_with_its_stack():
    processes = Processes()
    try:
        proc = processes.start(sys.executable, "-c", HANG)
        with pytest.raises(pytest.fail.Exception, match=r"(?s)still ran after 1 s.*stuck_here"):
            finish(proc, timeout=1)
        assert proc.poll() is not None  # aborted, not left running
    finally:
        processes.close()
