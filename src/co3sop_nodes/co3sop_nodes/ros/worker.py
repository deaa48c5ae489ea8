"""A node's compute on its own thread, so the executor keeps taking messages while a frame is computed.

With the model on the executor's thread, messages that arrive during a frame
wait in DDS's queue and are taken one per subscription per frame afterwards:
a node slower than its input works through a backlog, frame by frame, and
its latency grows with the queue. On its own thread the node sees every
message as it comes and can choose the newest work (PyTorch and the compiled
kernels release the GIL while they compute).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from co3sop_nodes.common.errors import exception_line


class Worker:
    """Calls `take()` under `lock` whenever woken (and every `poll_s`, for a `take` with deadlines; None: only when
    woken); a callable it returns is run outside the lock, on the worker's thread. Callbacks that change what `take`
    looks at hold `lock` and then call `wake()`."""

    def __init__(self, name: str, take: Callable[[], Callable[[], None] | None], logger, poll_s: float | None = 0.02):
        self.lock = threading.Lock()
        self._cond = threading.Condition(self.lock)
        self._name, self._take, self._logger, self._poll_s = name, take, logger, poll_s
        self._thread: threading.Thread | None = None
        self._running = False

    def start(self) -> None:
        self._running = True
        self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stops taking work and waits for the job in progress to end."""
        with self._cond:
            self._running = False
            self._cond.notify()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None

    def wake(self) -> None:
        """Call with `lock` held."""
        self._cond.notify()

    def wait_for(self, ready: Callable[[], bool], timeout_s: float) -> bool:
        """From a job: waits, at most `timeout_s`, until `ready()` (checked under `lock` whenever a callback wakes the
        worker) or the worker stops; whether it is ready."""
        with self._cond:
            self._cond.wait_for(lambda: ready() or not self._running, timeout_s)
            return ready()

    def _loop(self) -> None:
        while True:
            with self._cond:
                job = None
                while self._running and (job := self._take()) is None:
                    self._cond.wait(self._poll_s)
                if not self._running:
                    return
            try:
                job()
            except Exception as exc:
                self._logger.error(f"{self._name}: a frame failed: {exception_line(exc)}")
