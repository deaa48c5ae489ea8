"""DropLog: drops counted by kind, one warning per burst."""

from __future__ import annotations

import time

from co3sop_nodes.ros.dds import DropLog


def test_a_burst_is_logged_once_and_counted_in_full(logger):
    drops = DropLog(logger, quiet=0.2)
    for i in range(1000):
        drops("/cav_7/voxel_features", "malformed", f"{i} bytes that are not a valid VoxelFeatures")
    drops("/cav_7/voxel_features", "payload", "values: truncated")  # another kind of reason: its own warning
    drops("/cav_8/voxel_features", "malformed", "3 bytes that are not a valid VoxelFeatures")  # another topic too
    assert (
        len(logger.warnings) == 3
        and logger.warnings[0]
        == "/cav_7/voxel_features: dropped (malformed): 0 bytes that are not a valid VoxelFeatures"
    )
    assert drops.values() == {"dropped": 1002, "dropped_malformed": 1001, "dropped_payload": 1}
    time.sleep(0.25)  # the burst is over: the next one is logged, with how many were not
    drops("/cav_7/voxel_features", "malformed", "5 bytes that are not a valid VoxelFeatures")
    assert logger.warnings[-1].endswith("(999 more like it not logged)")


def test_many_distinct_reasons_keep_memory_bounded(logger):
    drops = DropLog(logger, quiet=0.0, max_keys=16)
    for i in range(1000):
        drops(f"/cav_{i}/voxel_features", "malformed", "x")
    assert len(drops._bursts) <= 16 and drops.counts["malformed"] == 1000
