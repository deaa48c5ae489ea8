"""Two OS processes exchange VoxelFeatures and SemanticOccupancy over real DDS."""

from __future__ import annotations

import json
import sys

from conftest import HERE, finish

sys.path.insert(0, str(HERE / "peers"))
from cases import CASES, encoded
from digest import decoded_digest


def test_every_payload_decodes_bit_exact_in_another_process(processes, tmp_path):
    out = tmp_path / "received.json"
    receiver = processes.peer("exchange.py", "receive", str(out))
    publisher = processes.peer("exchange.py", "publish")
    code, log = finish(publisher)
    assert code == 0, log
    code, log = finish(receiver)
    assert code == 0, log
    received = {int(k): v for k, v in json.loads(out.read_text()).items()}
    assert sorted(received) == list(range(len(CASES)))
    largest = 0
    for index in range(len(CASES)):
        enc = encoded(index)
        assert received[index]["payload_bytes"] == enc.payload_bytes, f"case {index}"
        assert received[index]["digest"] == decoded_digest(enc), f"case {index} decoded differently"
        largest = max(largest, enc.payload_bytes)
    assert largest >= 4 * 1024 * 1024  # the multi-megabyte payloads really crossed
