"""A bag's messages at their recorded pace, scaled by a rate (ROS-free: the player publishes what it yields).

The schedule starts when the first message is in hand, not when reading starts: opening a bag's first chunk
takes milliseconds (more on a loaded machine), and a schedule started before it would send the first frame late
and the second on time, closer to the first than the bag's period, bunching the graph's busiest frame, its
first, with the next.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

M = TypeVar("M")


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
