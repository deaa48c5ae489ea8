"""co3sop_nodes.v2x.sender_frames: a vehicle's messages grouped into frames by stamp (late, missing, repeated and
interleaved parts)."""

from __future__ import annotations

import pytest

from co3sop_nodes.v2x.sender_frames import FrameAssembly

PARTS = ("pose", "image:camera0", "info:camera0")


def feed(a: FrameAssembly, stamp: int, parts=PARTS, msg="m"):
    frames, drops = [], []
    for p in parts:
        f, d = a.add(p, stamp, f"{msg}{stamp}{p}", wall_ns=1000 + stamp)
        frames += f
        drops += d
    return frames, drops


def test_a_frame_comes_out_once_when_its_last_part_arrives():
    a = FrameAssembly(PARTS)
    frames, drops = feed(a, 10, PARTS[:-1])
    assert frames == [] and drops == []
    frames, drops = a.add("info:camera0", 10, "late info", wall_ns=5)
    assert [f.stamp for f in frames] == [10] and drops == []
    assert (
        frames[0].parts["info:camera0"] == "late info" and frames[0].first_wall_ns == 1010
    )  # when the first part came
    assert a.ready() == ([], [])


def test_interleaved_frames_come_out_oldest_first():
    a = FrameAssembly(PARTS)
    out = []
    for p in PARTS[:-1]:  # topics carry no order between them: the next frame's parts arrive in between
        for stamp in (20, 10):
            out += [f.stamp for f in a.add(p, stamp, p, 0)[0]]
    for stamp in (10, 20):
        out += [f.stamp for f in a.add(PARTS[-1], stamp, "last", 0)[0]]
    assert out == [10, 20]


def test_a_part_of_a_frame_already_out_is_stale():
    a = FrameAssembly(PARTS)
    feed(a, 10)
    frames, drops = a.add("pose", 10, "again", 0)
    assert frames == [] and [(d.part, d.kind) for d in drops] == [("pose", "stale")]
    frames, drops = a.add("pose", 5, "older", 0)
    assert frames == [] and drops[0].kind == "stale" and "not newer than the last encoded frame 10" in drops[0].reason


def test_a_repeated_part_replaces_the_earlier_copy():
    a = FrameAssembly(PARTS)
    a.add("pose", 10, "first", 0)
    a.add("pose", 10, "second", 0)
    frames, _ = feed(a, 10, PARTS[1:])
    assert frames[0].parts["pose"] == "second"


def test_an_overtaken_frame_is_dropped_as_incomplete_naming_what_it_lacks():
    a = FrameAssembly(PARTS)
    feed(a, 10, ("pose", "image:camera0"))
    frames, drops = feed(a, 20)
    assert [f.stamp for f in frames] == [20]
    assert [(d.part, d.kind) for d in drops] == [("info:camera0", "incomplete")]
    assert "frame 10 incomplete (no info:camera0)" in drops[0].reason


def test_incomplete_frames_do_not_pile_up():
    a = FrameAssembly(PARTS, max_pending=3)
    drops = []
    for stamp in range(10, 80, 10):  # never complete: only poses
        drops += a.add("pose", stamp, "p", 0)[1]
    assert [d.reason.split()[1] for d in drops] == ["10", "20", "30", "40"]
    assert all(d.kind == "incomplete" and "after 3 newer frames" in d.reason for d in drops)


def test_a_frame_waits_for_its_requirement_and_comes_out_when_asked_again():
    mounts: set[str] = set()
    a = FrameAssembly(PARTS, complete=lambda parts: "camera0" in mounts, requirement="camera mounts")
    frames, drops = feed(a, 10)
    assert frames == [] and drops == []
    mounts.add("camera0")  # /tf_static arrived
    frames, drops = a.ready()
    assert [f.stamp for f in frames] == [10] and drops == []


def test_requirement_never_met_is_named():
    a = FrameAssembly(PARTS, max_pending=1, complete=lambda parts: False, requirement="camera mounts")
    feed(a, 10)
    _, drops = feed(a, 20)
    assert drops and "no camera mounts" in drops[0].reason and drops[0].part is None


def test_unknown_part_is_an_error():
    with pytest.raises(ValueError, match="unknown part"):
        FrameAssembly(PARTS).add("lidar", 1, None, 0)
