"""A Foxglove layout for a recording: the ego's prediction and its ground truth as coloured points side by side,
its four cameras below (ROS-free; the JSON Foxglove imports with Layouts -> Import from file)."""

from __future__ import annotations

import json
from pathlib import Path

from co3sop_nodes.common import topics

CAMERAS = ("camera0", "camera1", "camera2", "camera3")  # front, right, left, back


def _points_panel(topic: str, frame: str) -> dict:
    return {
        "followTf": frame,
        "followMode": "follow-pose",
        "cameraState": {
            "perspective": True,
            "distance": 70.0,
            "phi": 55.0,
            "thetaOffset": 90.0,
            "targetOffset": [0, 0, 0],
        },
        "topics": {
            topic: {"visible": True, "colorMode": "rgb", "colorField": "rgb", "pointShape": "square", "pointSize": 3}
        },
    }


def layout(ego_id: int, cameras: tuple[str, ...] = CAMERAS, every_cav_an_ego: bool = False) -> dict:
    """Top: /ego/occupancy/points | /ego/ground_truth/points in the ego's LiDAR frame (under /cav_<ego_id> where
    every CAV runs an ego); bottom: the ego's cameras."""
    frame, ns = topics.lidar_frame(ego_id), ego_id if every_cav_an_ego else None
    config = {
        "3D!prediction": _points_panel(topics.ego_output(topics.EGO_POINTS, ns), frame),
        "3D!ground_truth": _points_panel(topics.ego_output(topics.EGO_TRUTH_POINTS, ns), frame),
    }
    row: str | dict = ""
    for cam in reversed(cameras):  # a right-leaning split tree, equal shares
        key = f"Image!{cam}"
        config[key] = {"imageMode": {"imageTopic": topics.camera_image(ego_id, cam)}}
        row = (
            key
            if not row
            else {"direction": "row", "first": key, "second": row, "splitPercentage": 100 / (1 + _leaves(row))}
        )
    return {
        "configById": config,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1.0},
        "layout": {
            "direction": "column",
            "splitPercentage": 65,
            "first": {"direction": "row", "first": "3D!prediction", "second": "3D!ground_truth", "splitPercentage": 50},
            "second": row,
        },
    }


def _leaves(tree: str | dict) -> int:
    return 1 if isinstance(tree, str) else _leaves(tree["first"]) + _leaves(tree["second"])


def write_layout(path: Path, ego_id: int, every_cav_an_ego: bool = False) -> Path:
    path.write_text(json.dumps(layout(ego_id, every_cav_an_ego=every_cav_an_ego), indent=2) + "\n")
    return path
