"""A bag's messages at their recorded pace, scaled by a rate, read ahead of it (ROS-free: the player publishes
what `paced` yields).

Reading is not on the schedule's path: a thread reads the bag into a bounded queue (`ReadAhead`, as `ros2 bag
play` reads ahead into its own), and playing starts once that queue is full or the bag read. A chunk read from
disk takes milliseconds and, on a shared disk, now and then hundreds: read in turn with publishing, one slow
read holds back every message after it and then sends them in a burst, several frames at once, which a graph
at its sensors' rate cannot take. The schedule starts when the first message is in hand, so the first frame is
not sent late and the second on time, bunched with it.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Generic, TypeVar

M = TypeVar("M")

_END = object()  # the source is exhausted


class ReadAhead(Generic[M]):
    """Iterates `messages` read on a thread of its own, at most `size` messages ahead of the consumer; the
    source's exception, if it raises, is raised to the consumer where the messages stop. `close()` (or the end of
    iteration) stops the thread; use as a context manager."""

    def __init__(self, messages: Iterable[M], size: int):
        if size < 1:
            raise ValueError(f"read-ahead size {size}: at least 1")
        self._queue: queue.Queue = queue.Queue(maxsize=size)
        self._stop = threading.Event()
        self._done = threading.Event()  # the source is exhausted or failed: nothing more will be queued
        self._thread = threading.Thread(target=self._read, args=(iter(messages),), name="read-ahead", daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _read(self, messages: Iterator[M]) -> None:
        try:
            for message in messages:
                if not self._put(message):
                    return
            self._put(_END)
        except BaseException as exc:  # raised again on the consumer's side
            self._put(exc)
        finally:
            self._done.set()

    def fill(self, timeout: float | None = None) -> None:
        """Waits until the queue is full or the source is read (at most `timeout` s)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._done.is_set() and not self._queue.full():
            if deadline is not None and time.monotonic() >= deadline:
                return
            self._done.wait(0.01)

    def __iter__(self) -> Iterator[M]:
        try:
            while (item := self._queue.get()) is not _END:
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join()

    def __enter__(self) -> ReadAhead[M]:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def paced(
    messages: Iterable[M],
    stamp_of: Callable[[M], int],
    rate: float,
    start_ns: int,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> Iterator[M]:
    """Each message of `messages` once its recorded stamp (ns, `stamp_of`), counted from `start_ns` and divided by
    `rate`, has passed since the first message was read; a message already due (the reader fell behind) at once."""
    wall0 = None
    for message in messages:
        if wall0 is None:
            # the first message's own offset from start_ns still counts: `start` may fall before it
            wall0 = clock()
        delay = (stamp_of(message) - start_ns) / 1e9 / rate - (clock() - wall0)
        if delay > 0:
            sleep(delay)
        yield message
