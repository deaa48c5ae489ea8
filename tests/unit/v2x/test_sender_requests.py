"""co3sop_nodes.v2x.sender_requests: what a request map may cost its sender, whoever sends it. Times are passed in."""

from __future__ import annotations

import numpy as np

from co3sop_nodes.v2x.sender_requests import Request, RequestBook, union_request

S = 1_000_000_000
HERE = np.eye(4)


def at(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = x
    return pose


def request(x: float, t: float = 0.0, fill: float = 1.0) -> Request:
    return Request(np.full((4, 4, 2), fill, np.float32), at(x), int(t * S))


def book(**kw) -> RequestBook:
    return RequestBook(**{"comm_range": 70.0, "timeout_ns": 1 * S, "max_egos": 2, "capacity": 8, **kw})


def alive(_topic: str) -> bool:
    return True


def test_an_ego_id_is_taken_from_its_first_topic_until_that_topic_has_no_publisher():
    b = book()
    assert b.offer("/ego/request_map", 5, request(10), HERE, alive) is None
    spoof = b.offer("/spoof", 5, request(10, fill=0.0), HERE, alive)
    assert spoof.kind == "request_topic" and "/ego/request_map" in spoof.reason
    assert b.serving(0, HERE)[5].need.max() == 1.0  # the real ego's answers are untouched
    assert b.offer("/spoof", 5, request(10, fill=0.0), HERE, lambda topic: topic != "/ego/request_map") is None
    assert b.serving(0, HERE)[5].need.max() == 0.0  # its publisher gone, the id moved


def test_a_request_from_beyond_comm_range_is_refused():
    b = book()
    refused = b.offer("/far", 9, request(120), HERE, alive)
    assert refused.kind == "request_range" and "120 m" in refused.reason and len(b) == 0
    assert b.offer("/far", 9, request(120), None, alive) is None  # no pose of its own yet: kept, then judged per frame
    assert b.serving(0, HERE) == {}


def test_each_frame_answers_the_nearest_fresh_requests_only():
    b = book()
    for ego, x in ((1, 50), (2, 10), (3, 30)):
        b.offer(f"/e{ego}", ego, request(x), HERE, alive)
    assert list(b.serving(0, HERE)) == [2, 3]
    assert b.serving(int(1.5 * S), HERE) == {} and len(b) == 0  # expired and forgotten


def test_requests_age_in_sensor_time_whatever_the_play_rate():
    """A request is a frame or two old when it is answered: its stamp against the frame's, not when it came."""
    b = book()
    b.offer("/e1", 1, request(10, t=5.0), HERE, alive)
    assert list(b.serving(int(5.9 * S), HERE)) == [1]  # 0.9 s of sensor time later, however long that took
    b.offer("/e2", 2, request(10, t=9.0), HERE, alive)  # stamped far ahead of the frames: kept, not served
    assert list(b.serving(int(6.0 * S), HERE)) == [1]
    assert list(b.serving(int(7.0 * S), HERE)) == [] and len(b) == 1  # the first expired; the second waits
    assert list(b.serving(int(8.5 * S), HERE)) == [2]


def test_memory_stays_flat_under_thousands_of_ids_and_a_flood_does_not_push_out_a_near_ego():
    b = book()
    b.offer("/ego/request_map", 1, request(10), HERE, alive)
    for ego in range(100, 3100):
        b.offer(f"/fake{ego}", ego, request(20 + ego % 7, t=ego * 1e-5), HERE, alive)
    assert len(b) == 8 and len(b._topics) == 8
    assert list(b.serving(int(0.04 * S), HERE))[0] == 1  # the near ego is kept and answered first
    unplaced = book()  # before the vehicle knows its own pose: the oldest go first
    for ego in range(3000):
        unplaced.offer(f"/fake{ego}", ego, request(5, t=ego * 1e-4), None, alive)
    assert sorted(unplaced._requests) == list(range(2992, 3000))


def test_a_union_of_requests_asks_the_egos_mean_need():
    a = np.array([[[0.0, 0.5]], [[1.0, 0.2]]], np.float32)
    b = np.array([[[0.3, 0.1]], [[0.0, 0.9]]], np.float32)
    assert np.allclose(union_request([a, b]), np.array([[[0.15, 0.3]], [[0.5, 0.55]]], np.float32))
    assert np.array_equal(union_request([a]), a)


def test_a_frame_waits_for_the_maps_made_for_it_from_the_egos_it_serves_only():
    b = book()
    live = ["/e1", "/e2", "/own", "/far", "/quiet"]
    assert b.awaiting(0, live, first=True) == live  # the first frame waits for every ego yet unheard
    assert b.awaiting(0, live, first=False) == []  # later frames only for those heard from
    b.offer("/e1", 1, request(10, t=0.0), HERE, alive)
    b.offer("/e2", 2, request(20, t=0.0), HERE, alive)
    b.offer("/far", 9, request(120, t=0.0), HERE, alive)  # refused: never waited for
    b.heard("/own", 0)  # this vehicle's own ego: not served, not waited for
    assert b.awaiting(0, live, first=False) == []  # every map of this frame is in
    assert b.awaiting(int(0.1 * S), live, first=False) == ["/e1", "/e2"]  # the next frame's are not
    b.offer("/e1", 1, request(10, t=0.1), HERE, alive)
    assert b.awaiting(int(0.1 * S), live, first=False) == ["/e2"]
    assert b.awaiting(int(0.14 * S), ["/e1"], first=False) == []  # within half a frame: the same frame's map
    assert b.awaiting(int(1.2 * S), live, first=False) == []  # an ego silent for longer than the timeout
    assert b.awaiting(int(0.2 * S), ["/e2"], first=False) == ["/e2"]
    b.release("/e2")
    assert b.awaiting(int(0.2 * S), ["/e2"], first=False) == []


def test_a_map_older_than_the_one_held_is_refused_and_leaves_the_wait_as_it_was():
    b = book()
    assert b.offer("/e1", 1, request(10, t=0.5, fill=1.0), HERE, alive) is None
    stale = b.offer("/e1", 1, request(10, t=0.2, fill=0.0), HERE, alive)  # a replay, or a stand-in's repeat
    assert stale.kind == "request_stale" and "older" in stale.reason
    assert b.serving(int(0.5 * S), HERE)[1].need.max() == 1.0  # the newer map is kept
    assert b.awaiting(int(0.6 * S), ["/e1"], first=False) == ["/e1"]  # still waited for, from its newest map on
    assert b.awaiting(int(0.5 * S), ["/e1"], first=False) == []


def test_a_frame_behind_its_egos_answers_the_map_made_for_it_not_a_later_one():
    """A vehicle running a frame behind: the ego's maps of 0.1 and 0.2 are both in when it encodes its frame of 0.1."""
    b = book(depth=2)
    for t, fill in ((0.0, 0.25), (0.1, 0.5), (0.2, 1.0)):
        assert b.offer("/e1", 1, request(10, t=t, fill=fill), HERE, alive) is None
    assert b.serving(int(0.1 * S), HERE)[1].stamp == int(0.1 * S)
    assert b.serving(int(0.12 * S), HERE)[1].stamp == int(0.1 * S)  # within half a frame: the same frame's map
    assert b.serving(int(0.2 * S), HERE)[1].need.max() == 1.0
    assert b.serving(int(0.05 * S), HERE)[1].stamp == int(0.1 * S)  # its own fell out of the depth: the nearest held
    assert b.offer("/e1", 1, request(10, t=0.2, fill=0.0), HERE, alive) is None  # a map of the same frame replaces it
    assert [r.need.max() for r in b._requests[1]] == [0.5, 0.0]
