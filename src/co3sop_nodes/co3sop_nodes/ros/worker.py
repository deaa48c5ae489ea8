"""A node's compute on its own thread, so the executor keeps taking messages while a frame is computed.

With the model on the executor's thread, messages that arrive during a frame
wait in DDS's queue and are taken one per subscription per frame afterwards:
a node slower than its input works through a backlog, frame by frame, and
its latency grows with the queue. On its own thread the node sees every
message as it comes and can choose the newest work (PyTorch and the compiled
kernels release the GIL while they compute).

The thread lives as long as the node, so the node can warm up on the thread
that computes its frames (`call`).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import TypeVar

from co3sop_nodes.common.errors import exception_line

T = TypeVar("T")


class Worker:
    """Between `start()` and `stop()`, calls `take()` under `lock` whenever woken (and every `poll_s`, for a `take`
    with deadlines; None: only when woken); a callable it returns is run outside the lock, on the worker's thread.
    Callbacks that change what `take` looks at hold `lock` and then call `wake()`. `close()` ends the thread."""

    def __init__(self, name: str, take: Callable[[], Callable[[], None] | None], logger, poll_s: float | None = 0.02):
        self.lock = threading.Lock()
        self._cond = threading.Condition(self.lock)
        self._name, self._take, self._logger, self._poll_s = name, take, logger, poll_s
        self._running = False  # taking work
        self._busy = False  # a job or a call in progress
        self._closed = False
        self._calls: deque[Callable[[], None]] = deque()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def call(self, fn: Callable[[], T]) -> T:
        """fn() on the worker's thread (after the job in progress), its result or its exception."""
        if threading.current_thread() is self._thread:
            return fn()
        done, out = threading.Event(), {}

        def run() -> None:
            try:
                out["value"] = fn()
            except BaseException as exc:  # re-raised on the caller's thread
                out["error"] = exc
            finally:
                done.set()

        with self._cond:
            if self._closed:
                raise RuntimeError(f"{self._name}: the worker is closed")
            self._calls.append(run)
            self._cond.notify_all()
        done.wait()
        if "error" in out:
            raise out["error"]
        return out["value"]

    def start(self) -> None:
        with self._cond:
            self._running = True
            self._cond.notify_all()

    def stop(self) -> None:
        """Stops taking work and waits for the job in progress to end (unless called from that job)."""
        with self._cond:
            self._running = False
            self._cond.notify_all()
            if threading.current_thread() is not self._thread:
                self._cond.wait_for(lambda: not self._busy)

    def close(self) -> None:
        """Stops, and ends the thread."""
        self.stop()
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if threading.current_thread() is not self._thread:
            self._thread.join()

    def wake(self) -> None:
        """Call with `lock` held."""
        self._cond.notify_all()

    def wait_for(self, ready: Callable[[], bool], timeout_s: float) -> bool:
        """From a job: waits, at most `timeout_s`, until `ready()` (checked under `lock` whenever a callback wakes the
        worker) or the worker stops; whether it is ready."""
        with self._cond:
            self._cond.wait_for(lambda: ready() or not self._running, timeout_s)
            return ready()

    def _next(self) -> Callable[[], None] | None:
        """With `lock` held: a call, else (while running) a job take() hands out."""
        if self._calls:
            return self._calls.popleft()
        return self._take() if self._running else None

    def _loop(self) -> None:
        while True:
            with self._cond:
                while (job := self._next()) is None and not self._closed:
                    self._cond.wait(self._poll_s if self._running else None)
                if job is None:  # closed, every call answered
                    return
                self._busy = True
            try:
                job()
            except Exception as exc:
                self._logger.error(f"{self._name}: a frame failed: {exception_line(exc)}")
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()
