"""What the benchmark scripts share: median timing of repeated calls."""

from __future__ import annotations

import statistics
import time


def timed(fn, repeats: int) -> tuple[float, object]:
    """Median seconds of `repeats` calls, and the last result."""
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def alternated(groups: dict, repeats: int, finish=None, block: int = 4) -> dict:
    """Median seconds of every call of `groups` (group -> {key: fn}), `repeats` timed calls each, the groups taking
    turns: a turn calls its group's functions in order `block` times over, the first time untimed (its caches are
    the other groups'), so each is timed as it runs on its own while a spell of a shared machine's noise falls on
    every group alike and their ratios hold within a run. `finish()` ends each call where given (a GPU's
    synchronisation). -> {(group, key): seconds}."""
    times = {(group, key): [] for group, calls in groups.items() for key in calls}
    while any(len(t) < repeats for t in times.values()):
        for group, calls in groups.items():
            for turn in range(block):
                for key, fn in calls.items():
                    t0 = time.perf_counter()
                    fn()
                    if finish is not None:
                        finish()
                    if turn and len(times[group, key]) < repeats:
                        times[group, key].append(time.perf_counter() - t0)
    return {key: statistics.median(t) for key, t in times.items()}
