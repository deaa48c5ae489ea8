"""The player's pace: recorded stamps scaled by the rate, counted from the first message read (no DDS, a fake
clock)."""

import threading

import pytest

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.data.playback import ReadAhead, paced

MS = 1_000_000


class FakeTime:
    def __init__(self):
        self.now = 0.0
        self.sleeps = []

    def clock(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.now += s


def played(stamps, rate=1.0, start=0, first_read_s=0.0, read_s=0.0):
    """(stamp, the fake time it was yielded at) for each stamp; reading the first message takes first_read_s,
    every later one read_s."""
    t = FakeTime()

    def messages():
        for i, s in enumerate(stamps):
            t.now += first_read_s if i == 0 else read_s
            yield s

    return [(s, round(t.now, 9)) for s in paced(messages(), lambda s: s, rate, start, t.clock, t.sleep)], t


def test_messages_go_out_at_their_stamps_over_the_rate():
    out, _ = played([0, 100 * MS, 200 * MS], rate=0.5)
    assert out == [(0, 0.0), (100 * MS, 0.2), (200 * MS, 0.4)]


def test_the_schedule_starts_when_the_first_message_is_read():
    # a slow first read (the bag's first chunk) delays the whole schedule, not only the first frame: the second
    # frame still comes a period after the first
    out, _ = played([0, 100 * MS, 200 * MS], first_read_s=0.25)
    assert [t for _, t in out] == [0.25, 0.35, 0.45]


def test_the_first_message_keeps_its_offset_from_the_start():
    out, _ = played([50 * MS, 150 * MS], start=0)
    assert [t for _, t in out] == [0.05, 0.15]


def test_a_reader_behind_its_schedule_sends_at_once_and_catches_up():
    out, t = played([0, 100 * MS, 200 * MS, 300 * MS], read_s=0.15)
    assert [t for _, t in out] == [0.0, 0.15, 0.3, 0.45]
    assert t.sleeps == []


def test_read_ahead_yields_every_message_in_order_and_stays_within_its_bound():
    read = []

    def source():
        for i in range(50):
            read.append(i)
            yield i

    ahead = ReadAhead(source(), size=5)
    ahead.fill()
    # full: the queue's 5, and at most the one the reader holds while it waits for room
    assert 5 <= len(read) <= 6
    assert list(ahead) == list(range(50))


def test_read_ahead_fill_returns_when_the_source_is_shorter_than_the_queue():
    with ReadAhead(iter([1, 2]), size=100) as ahead:
        ahead.fill(timeout=10)
        assert list(ahead) == [1, 2]


def test_read_ahead_raises_the_source_error_where_the_messages_stop():
    def source():
        yield 1
        raise DatasetError("bag.mcap: a truncated chunk")

    got = []
    with pytest.raises(DatasetError, match="truncated chunk"):
        for m in ReadAhead(source(), size=10):
            got.append(m)
    assert got == [1]


def test_read_ahead_closed_early_stops_its_reader():
    def endless():
        i = 0
        while True:
            yield i
            i += 1

    ahead = ReadAhead(endless(), size=3)
    for m in ahead:
        if m == 10:
            break
    ahead.close()
    assert not any(t.name == "read-ahead" and t.is_alive() for t in threading.enumerate())


def test_read_ahead_needs_room_for_one_message():
    with pytest.raises(ValueError, match="at least 1"):
        ReadAhead(iter([]), size=0)
