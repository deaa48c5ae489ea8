"""A process that keeps its freed memory serves a frame's large blocks without asking the kernel for new pages."""

import gc
import platform
import subprocess
import sys

import pytest

from co3sop_nodes.common.allocation import MAX_RESERVE, freeze_setup, reserve_memory

# minor page faults of 20 rounds of a 40 MB block (beyond the 32 MB malloc adapts to) written, then freed, after
# a first round
_FAULTS = """
import resource, sys
if sys.argv[1] == "keep":
    from co3sop_nodes.common.allocation import keep_freed_memory
    assert keep_freed_memory()
def frame():
    block = bytearray(40 << 20)  # malloc's own pages (numpy would ask the kernel for huge pages)
    block[::4096] = bytes(len(block) // 4096)  # a write to every page
    del block
frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    frame()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> int:
    done = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True)
    return int(done.stdout)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")
def test_kept_memory_serves_repeated_large_blocks_without_new_pages():
    default, kept = _faults("default"), _faults("keep")
    assert default > 20 * 5000  # each round faults in its 10240 pages anew: what the setting is for
    assert kept < 200  # the first round's pages serve every later one


# minor page faults of four threads other than the reserving one, each writing 28 MB (7 blocks of 4 MB) while the
# others hold theirs, after 128 MB reserved (or not) by the main thread; imported as a node process imports them,
# numpy and rclpy starting threads of their own after the node package (threads after those took arenas of their
# own if malloc was set up too late)
_RESERVED = """
import resource, sys, threading
import co3sop_nodes.ros
import numpy, rclpy
from co3sop_nodes.common.allocation import reserve_memory
assert reserve_memory(int(sys.argv[1]) << 20) == (sys.argv[1] != "0")
together = threading.Barrier(4)
def frame():
    blocks = [bytearray(4 << 20) for _ in range(7)]
    for block in blocks:
        block[::4096] = bytes(len(block) // 4096)
    together.wait()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
workers = [threading.Thread(target=frame) for _ in range(4)]
for worker in workers:
    worker.start()
for worker in workers:
    worker.join()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults_after_reserve(mb: int) -> int:
    done = subprocess.run([sys.executable, "-c", _RESERVED, str(mb)], capture_output=True, text=True, check=True)
    return int(done.stdout)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")
def test_memory_reserved_by_one_thread_serves_a_node_processes_other_threads_without_new_pages():
    none, reserved = _faults_after_reserve(0), _faults_after_reserve(128)
    assert none > 25_000  # 28672 pages written for the first time
    assert reserved < 1_000  # the reserve's pages, though other threads wrote and freed them


def test_a_reserve_beyond_what_the_trim_threshold_holds_is_refused():
    with pytest.raises(ValueError, match="trim threshold"):
        reserve_memory(MAX_RESERVE + 1)


def test_freeze_setup_takes_live_objects_out_of_the_collector():
    try:
        before = gc.get_freeze_count()
        kept = [object() for _ in range(1000)]
        freeze_setup()
        assert gc.get_freeze_count() >= before + len(kept)
    finally:
        gc.unfreeze()
