"""co3sop_nodes.v2x.ego_pairing: which of the ego's frames to fuse when, with which neighbours (late, missing,
silent, out-of-order and duplicate frames). Times are passed in: no clock, no DDS."""

from __future__ import annotations

from dataclasses import replace

from co3sop_nodes.v2x.ego_pairing import Pairing, PairingConfig

EGO, A, B = 1, 2, 3
MS = 1_000_000
S = 1_000_000_000
CFG = PairingConfig(tolerance_ns=50 * MS, max_wait_s=2.0, neighbour_timeout_ns=5 * S, max_age_ns=0)


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


def test_an_own_frame_older_than_a_ready_one_is_skipped_and_old_neighbour_frames_are_forgotten():
    c = Clock()
    p = make(A, clock=c)
    for s in (0, 100 * MS, 200 * MS):
        add(p, A, s, c)
    add(p, EGO, 200 * MS, c)
    add(p, EGO, 100 * MS, c)  # out of order
    assert due(p, c) == [200 * MS] and p.skipped == 1
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


def test_a_repeated_own_frame_is_fused_once():
    c = Clock()
    p = make(A, clock=c)
    add(p, A, 100 * MS, c)
    add(p, EGO, 100 * MS, c)
    add(p, EGO, 100 * MS, c)
    assert due(p, c) == [100 * MS] and p.skipped == 1


def test_a_graph_fed_faster_than_it_fuses_fuses_the_newest_ready_frame_and_skips_the_rest():
    """Ten frames arrive while one is fused: latency stays one frame, the nine older ones are counted."""
    c = Clock()
    p = make(A, B, clock=c)
    for k in range(10):
        for agent in (EGO, A, B):
            add(p, agent, k * 100 * MS, c)
        c.t += 0.1
    assert due(p, c) == [900 * MS] and p.skipped == 9


def test_the_newest_frame_that_can_still_pair_is_fused_while_a_newer_one_waits():
    c = Clock()
    p = make(A, clock=c)
    for k in range(3):
        add(p, EGO, k * 100 * MS, c)
        if k < 2:
            add(p, A, k * 100 * MS, c)
    assert due(p, c) == [100 * MS] and p.skipped == 1  # frame 200 ms still waits for A
    add(p, A, 200 * MS, c)
    assert due(p, c) == [200 * MS] and p.skipped == 1


def test_a_frame_waits_for_a_dead_neighbour_only_until_the_next_own_frame():
    """A neighbour that stopped sending (its publisher not yet gone): each own frame stops waiting when the next one
    comes, so latency is one frame period, not max_wait; with stay_current off, at most max_pending frames wait."""
    for stay_current, want in ((True, 7), (False, 5)):
        c = Clock()
        p = Pairing(EGO, replace(CFG, max_pending=3, stay_current=stay_current))
        p.discovered(A, c.wall)
        fused = []
        for k in range(8):
            add(p, EGO, k * 100 * MS, c)
            fused += due(p, c)
            c.t += 0.1
        assert fused == [k * 100 * MS for k in range(want)] and p.skipped == 0


def test_a_neighbour_that_skipped_the_frame_is_fused_with_its_nearest_within_max_age():
    c = Clock()
    p = Pairing(EGO, replace(CFG, max_age_ns=300 * MS))
    p.discovered(A, c.wall)
    add(p, A, 0, c)
    add(p, A, 400 * MS, c)  # A skipped 100..300 ms: slower than its sensors
    add(p, EGO, 200 * MS, c)
    assert due(p, c) == [200 * MS]  # A sent a newer frame: not waited for
    assert p.match(A, 200 * MS) is None and p.nearest(A, 200 * MS) == f"{A}@{0}"  # 200 ms away: both within max_age
    assert p.nearest(A, 800 * MS) is None and not p.stale(0) and p.stale(-101 * MS)


def test_with_stay_current_off_every_own_frame_is_fused_oldest_first():
    c = Clock()
    p = Pairing(EGO, replace(CFG, stay_current=False, max_pending=100))
    p.discovered(A, c.wall)
    for k in range(5):
        add(p, EGO, k * 100 * MS, c)
        add(p, A, k * 100 * MS, c)
    assert due(p, c) == [k * 100 * MS for k in range(5)] and p.skipped == 0


def test_an_own_frame_fused_or_waiting_is_known_as_repeated():
    c = Clock()
    p = make(A, clock=c)
    add(p, EGO, 100 * MS, c)
    assert p.repeated(100 * MS) and not p.repeated(200 * MS)
    add(p, A, 100 * MS, c)
    assert due(p, c) == [100 * MS]
    assert p.repeated(100 * MS) and p.repeated(90 * MS) and not p.repeated(101 * MS)
