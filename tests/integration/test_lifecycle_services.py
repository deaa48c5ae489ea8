"""Lifecycle services as any participant may call them: every transition id (and label) from every state, over
the real ChangeState service; one not valid from the current state is refused, and the node lives on."""

from __future__ import annotations

import signal

import pytest
import rclpy
from executables import executable, exit_code
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from test_node_faults import EGO, start, wait_for

from co3sop_nodes.common import topics

VALID = {
    "unconfigured": {Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN},
    "inactive": {
        Transition.TRANSITION_CLEANUP,
        Transition.TRANSITION_ACTIVATE,
        Transition.TRANSITION_INACTIVE_SHUTDOWN,
    },
    "active": {Transition.TRANSITION_DEACTIVATE, Transition.TRANSITION_ACTIVE_SHUTDOWN},
    "finalized": set(),
}
ROUTE = {
    "unconfigured": [],
    "inactive": [Transition.TRANSITION_CONFIGURE],
    "active": [Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE],
}
BACK = {
    "unconfigured": [],
    "inactive": [Transition.TRANSITION_CLEANUP],
    "active": [Transition.TRANSITION_DEACTIVATE, Transition.TRANSITION_CLEANUP],
}
IDS = [*range(1, 8), 42, 255]  # the seven primary transitions, an unknown id, the largest uint8


def ask(peer, client, tid: int = 0, label: str = "") -> bool:
    future = client.call_async(ChangeState.Request(transition=Transition(id=tid, label=label)))
    rclpy.spin_until_future_complete(peer, future, timeout_sec=120)
    assert future.done(), "no answer from change_state"
    return future.result().success


@pytest.mark.parametrize(
    ("name", "node", "argv"),
    [
        ("ego", "/ego", ["ego", "--ros-args", "-p", f"ego_id:={EGO}"]),
        ("vehicle", topics.vehicle_node(5), ["vehicle", "--id", "5", "--ros-args"]),
    ],
)
def test_every_transition_from_every_state_is_taken_or_refused_and_the_node_lives(
    tmp_path, peer, sup, name, node, argv
):
    proc, log = start(tmp_path, name, executable(argv[0]), *argv[1:], "-p", "autostart:=false")
    try:
        client = peer.create_client(ChangeState, f"{node}/change_state")
        assert client.wait_for_service(timeout_sec=60), log.read_text()
        for state in ("unconfigured", "inactive", "active"):
            for tid in ROUTE[state]:
                assert ask(peer, client, tid)
            assert sup.state(node) == state
            for tid in IDS:
                if tid in VALID[state]:
                    continue
                assert not ask(peer, client, tid), (state, tid)
                assert proc.poll() is None and sup.state(node) == state, log.read_text()
            for label in ("bogus", *(["activate"] if state != "inactive" else [])):
                assert not ask(peer, client, label=label) and sup.state(node) == state
            for tid in BACK[state]:
                assert ask(peer, client, tid)
        assert ask(peer, client, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN) and sup.state(node) == "finalized"
        for tid in IDS:
            assert not ask(peer, client, tid)
        assert proc.poll() is None and sup.state(node) == "finalized"
        wait_for(log, "refused: not valid from state 'finalized'", proc)
    finally:
        proc.send_signal(signal.SIGINT)
        assert exit_code(proc, log) == 0, log.read_text()
