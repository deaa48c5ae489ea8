"""The node's compute thread: warm-up calls and frames run on one thread that lives as long as the node."""

from __future__ import annotations

import threading
import time

import pytest

from co3sop_nodes.ros.worker import Worker


def test_calls_and_jobs_run_on_the_one_thread_and_only_jobs_wait_for_start(logger):
    ran: list[str] = []
    pending = [lambda: ran.append(threading.current_thread().name)]
    worker = Worker("w", lambda: pending.pop() if pending else None, logger, poll_s=None)
    assert worker.call(lambda: threading.current_thread().name) == "w"  # before start: calls run, jobs wait
    assert ran == [] and pending
    worker.start()
    deadline = time.monotonic() + 5
    while not ran and time.monotonic() < deadline:
        time.sleep(0.01)
    assert ran == ["w"]  # the frame ran on the thread the call ran on
    with pytest.raises(ZeroDivisionError):  # a call's error reaches its caller, the thread goes on
        worker.call(lambda: 1 / 0)
    assert worker.call(lambda: 7) == 7 and logger.errors == []
    worker.close()
    with pytest.raises(RuntimeError, match="closed"):
        worker.call(lambda: 0)


def test_stop_waits_for_the_job_in_progress_and_no_job_starts_after_it(logger):
    started, release, finished = threading.Event(), threading.Event(), threading.Event()
    jobs = [lambda: (started.set(), release.wait(5), finished.set())]
    worker = Worker("w", lambda: jobs.pop() if jobs else None, logger, poll_s=0.01)
    worker.start()
    assert started.wait(5)
    stopper = threading.Thread(target=worker.stop)
    stopper.start()
    time.sleep(0.05)
    assert stopper.is_alive()  # stop waits for the frame in progress
    release.set()
    stopper.join(5)
    assert not stopper.is_alive() and finished.is_set()
    jobs.append(lambda: pytest.fail("a job ran after stop"))
    time.sleep(0.05)
    assert jobs  # not taken while stopped
    worker.close()


def test_a_failing_job_is_logged_and_the_worker_goes_on(logger):
    jobs = [lambda: None, lambda: 1 / 0]
    worker = Worker("w", lambda: jobs.pop() if jobs else None, logger, poll_s=0.01)
    worker.start()
    deadline = time.monotonic() + 5
    while jobs and time.monotonic() < deadline:
        time.sleep(0.01)
    worker.close()
    assert not jobs and len(logger.errors) == 1 and "division by zero" in logger.errors[0]
