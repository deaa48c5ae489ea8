"""co3sop_nodes.pairing: which of the ego's frames to fuse when, with which neighbours (late, missing,
silent, out-of-order and duplicate frames). Times are passed in: no clock, no DDS."""

from __future__ import annotations

from co3sop_nodes.pairing import Pairing, PairingConfig

EGO, A, B = 1, 2, 3
MS = 1_000_000
S = 1_000_000_000
CFG = PairingConfig(tolerance_ns=50 * MS, max_wait_s=2.0, neighbour_timeout_ns=5 * S)


class Clock:
    """Wall ns and monotonic s moving together."""

    def __init__(self):
        self.t = 0.0

    @property
    def wall(self) -> int:
        return int(self.t * S)


def everyone(_: int) -> bool:
    return True


def make(*neighbours: int, clock: Clock) -> Pairing:
    p = Pairing(EGO, CFG)
    for n in neighbours:
        p.discovered(n, clock.wall)
    return p


def add(p: Pairing, agent: int, stamp: int, clock: Clock) -> None:
    p.add(agent, stamp, f"{agent}@{stamp}", clock.wall, clock.t)


def due(p: Pairing, clock: Clock, publishers=everyone) -> list[int]:
    out = []
    while (s := p.next_due(clock.wall, clock.t, publishers)) is not None:
        out.append(s)
        p.fused(s)
    return out


def test_a_frame_waits_for_a_late_neighbour_then_pairs_with_it():
    c = Clock()
    p = make(A, clock=c)
    add(p, EGO, 100 * MS, c)
    assert due(p, c) == []  # A's frame has not come
    c.t += 0.5
    add(p, A, 110 * MS, c)  # within the tolerance
    assert p.match(A, 100 * MS) == f"{A}@{110 * MS}"
    assert due(p, c) == [100 * MS]


def test_a_missing_neighbour_costs_at_most_max_wait():
    c = Clock()
    p = make(A, clock=c)
    add(p, EGO, 100 * MS, c)
    c.t += 1.9
    assert due(p, c) == []
    c.t += 0.2  # past max_wait
    assert due(p, c) == [100 * MS] and p.match(A, 100 * MS) is None


def test_a_neighbour_that_sent_a_newer_frame_skipped_this_one():
    c = Clock()
    p = make(A, clock=c)
    add(p, A, 300 * MS, c)
    add(p, EGO, 100 * MS, c)
    assert due(p, c) == [100 * MS]  # no wait: A will not send 100 ms any more


def test_silence_counts_from_the_first_own_frame_not_from_discovery():
    """Sensors that start long after the graph: the neighbour discovered 60 s earlier is still waited for."""
    c = Clock()
    p = make(A, clock=c)
    c.t += 60
    add(p, EGO, 100 * MS, c)
    assert A in p.live(c.wall, everyone)
    assert due(p, c) == []
    c.t += 0.3
    add(p, A, 100 * MS, c)
    assert due(p, c) == [100 * MS]


def test_a_neighbour_that_never_sends_stops_costing_once_the_ego_has_run_for_the_timeout():
    c = Clock()
    p = make(A, clock=c)
    add(p, EGO, 0, c)  # t = 0: the ego's frames start; A has 5 s to speak
    c.t = 2.0
    assert due(p, c) == [0]  # waited max_wait
    add(p, EGO, 1 * S, c)
    c.t = 4.0
    assert due(p, c) == [1 * S]  # waited max_wait again
    add(p, EGO, 2 * S, c)
    assert due(p, c) == []
    c.t = 5.0  # 5 s of own frames without a word from A: silent, no longer waited for
    assert due(p, c) == [2 * S]
    add(p, EGO, 3 * S, c)
    assert due(p, c) == [3 * S]


def test_a_neighbour_without_a_publisher_is_not_waited_for():
    c = Clock()
    p = make(A, clock=c)
    add(p, EGO, 100 * MS, c)
    assert due(p, c, publishers=lambda agent: agent != A) == [100 * MS]


def test_a_dead_neighbour_is_waited_for_until_its_timeout_then_not():
    c = Clock()
    p = make(A, clock=c)
    add(p, A, 0, c)
    add(p, EGO, 0, c)
    assert due(p, c) == [0]
    c.t += 1.0  # A dies: its publisher stays in the graph until DDS notices
    add(p, EGO, 1 * S, c)
    assert due(p, c) == []  # waited for
    c.t += 2.0
    assert due(p, c) == [1 * S]  # max_wait passed
    c.t += 3.0  # 6 s after A's last frame
    add(p, EGO, 6 * S, c)
    assert A not in p.live(c.wall, everyone) and due(p, c) == [6 * S]  # no more waiting
    assert p.heard() == [A]  # still reported (as missing)


def test_own_frames_are_fused_in_arrival_order_and_old_neighbour_frames_are_forgotten():
    c = Clock()
    p = make(A, clock=c)
    for s in (0, 100 * MS, 200 * MS):
        add(p, A, s, c)
    add(p, EGO, 200 * MS, c)
    add(p, EGO, 100 * MS, c)  # out of order
    assert due(p, c) == [200 * MS, 100 * MS]
    assert p.match(A, 0) is None  # older than the last fused frame beyond the tolerance: forgotten
    assert p.stale(100 * MS) and not p.stale(160 * MS)


def test_the_nearest_frame_within_the_tolerance_pairs():
    c = Clock()
    p = make(A, B, clock=c)
    for s in (90 * MS, 130 * MS):
        add(p, A, s, c)
    add(p, B, 40 * MS, c)  # 60 ms off: outside
    assert p.match(A, 100 * MS) == f"{A}@{90 * MS}"
    assert p.match(B, 100 * MS) is None


def test_a_repeated_own_frame_is_fused_twice_with_the_same_neighbours():
    c = Clock()
    p = make(A, clock=c)
    add(p, A, 100 * MS, c)
    add(p, EGO, 100 * MS, c)
    add(p, EGO, 100 * MS, c)
    assert due(p, c) == [100 * MS, 100 * MS]
