"""The Supervisor's waits against a real publisher of /diagnostics: what a wait in vain says."""

from __future__ import annotations

import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.ros.dds import DIAGNOSTICS_QOS


def test_a_wait_for_reports_in_vain_says_what_came_instead(peer, sup):
    pub = peer.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, DIAGNOSTICS_QOS)
    deadline = time.monotonic() + 30
    while not sup.reports("ego") and time.monotonic() < deadline:  # until the supervisor has matched
        values = [KeyValue(key="neighbours_used", value="0"), KeyValue(key="neighbours_missing", value="713")]
        pub.publish(DiagnosticArray(status=[DiagnosticStatus(name="ego", values=values)]))
        time.sleep(0.1)
    assert sup.wait_reports("ego", 1, 10)[-1] == {"neighbours_used": "0", "neighbours_missing": "713"}
    with pytest.raises(Co3sopError) as caught:
        sup.wait_reports("ego", 2, 0.5, lambda r: r["neighbours_used"] == "1")
    came = len(sup.reports("ego"))
    assert str(caught.value) == (
        f"waited 0.5 s for 2 /diagnostics reports of 'ego', in vain: {came} came, 0 of them as wanted; "
        "the last: neighbours_used=0, neighbours_missing=713"
    )
    with pytest.raises(Co3sopError, match=r"reports of 'vehicle cav_3', in vain: 0 came, 0 of them as wanted$"):
        sup.wait_reports("vehicle cav_3", 1, 0.2)
