"""learn/report.py's reading of a LiDAR gain short of its goal (ROS-free)."""

from __future__ import annotations

import json

from co3sop_nodes.learn.report import why_short


def test_a_short_gain_is_set_against_what_the_collaborators_see(tmp_path):
    observed = tmp_path / "observed-51.2m.json"
    assert why_short(observed) == ""  # not measured at that range: nothing claimed
    classes = {"road": {"voxels": 1000, "ego": 0.20, "ego+collaborators": 0.30},
               "building": {"voxels": 100000, "ego": 0.005, "ego+collaborators": 0.0062},
               "pole": {"voxels": 10, "ego": 0.1, "ego+collaborators": 0.5},
               "vehicle": {"voxels": 500, "ego": 0.06, "ego+collaborators": 0.09}}
    observed.write_text(json.dumps({"splits": ["test"], "range": "51.2m", "samples": 3, "classes": classes,
                                    "all": {"voxels": 101510, "ego": 0.036, "ego+collaborators": 0.0526}}))
    text = why_short(observed)
    assert "by 1.66 points only (3.60 % -> 5.26 %" in text
    # the three classes that gain the most hit voxels, most first: building 120, road 100, vehicle 15 (pole 4)
    assert "building +0.12 points, road +10.00 points, vehicle +3.00 points" in text and "pole" not in text
