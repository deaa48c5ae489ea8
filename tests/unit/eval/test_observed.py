"""learn.observed: the table of what the collaborators' LiDAR adds."""

from __future__ import annotations

from co3sop_nodes.eval.observed import observed_table


def test_table_lists_the_share_each_adds():
    result = {
        "samples": 2,
        "all": {"voxels": 10, "ego": 0.2, "ego+collaborators": 0.5},
        "classes": {"road": {"voxels": 10, "ego": 0.2, "ego+collaborators": 0.5}},
    }
    text = observed_table(result, "test, 51.2m")
    assert "| all occupied | 10 | 20.00 | 50.00 | 30.00 |" in text and "| road |" in text
