"""The ego's prediction and ground truth as coloured points (recording_clouds) and the Foxglove layout that shows
them (foxglove)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from co3sop_nodes.common import topics
from co3sop_nodes.common.classes import NUM_CLASSES
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.data.bags import typestore
from co3sop_nodes.messages import OCCUPANCY, RosbagsTypes, occupancy_msg
from co3sop_nodes.messages.sensors import POINT_CLOUD as POINTS
from co3sop_nodes.v2x.codec import encode_labels
from co3sop_nodes.viz.cloud import occupancy_cloud
from co3sop_nodes.viz.foxglove import CAMERAS, layout
from co3sop_nodes.viz.recording_clouds import RecordingClouds, is_drawn, truth_key

STORE = typestore()
EGO, OTHER = 3, 8


def occupancy(agent: int, range_name: str, stamp: int, seed: int = 0) -> tuple[bytes, np.ndarray]:
    grid = BENCHMARK_RANGES[range_name]
    labels = np.random.default_rng(seed).choice([0, 0, 0, 4, 7, 10, 255], size=grid.dims).astype(np.uint8)
    enc = encode_labels(labels, grid, NUM_CLASSES)
    msg = occupancy_msg(
        RosbagsTypes(STORE), enc, stamp_ns=stamp * 10**9, frame_id=topics.lidar_frame(agent), agent_id=agent
    )
    return bytes(STORE.serialize_cdr(msg, OCCUPANCY)), labels


def points_of(raw: bytes):
    return STORE.deserialize_cdr(raw, POINTS)


def test_truth_key_names_cav_and_range_of_ground_truth_topics_only():
    assert truth_key(topics.ground_truth(EGO, "51.2m")) == (EGO, "51.2m")
    assert truth_key(topics.ground_truth(OTHER, "25.6m")) == (OTHER, "25.6m")
    assert truth_key(topics.EGO_OCCUPANCY) is None and truth_key(topics.lidar_pose(EGO)) is None


def test_the_clouds_a_recording_draws_are_never_recorded_as_published():
    for cav in (None, EGO):
        assert is_drawn(topics.ego_output(topics.EGO_POINTS, cav))
        assert is_drawn(topics.ego_output(topics.EGO_TRUTH_POINTS, cav))
        assert not is_drawn(topics.ego_output(topics.EGO_OCCUPANCY, cav))
    assert not is_drawn("/ego/occupancy/points/extra") and not is_drawn(topics.lidar_points(EGO))


def test_an_egos_ground_truth_at_its_range_becomes_the_points_the_ego_publishes():
    conv = RecordingClouds()
    early, early_labels = occupancy(EGO, "51.2m", 1, seed=1)
    assert conv.truth(topics.ground_truth(EGO, "51.2m"), early) == []  # no prediction yet: it waits
    assert conv.truth(topics.ground_truth(EGO, "25.6m"), occupancy(EGO, "25.6m", 1)[0]) == []
    assert conv.truth(topics.ground_truth(OTHER, "51.2m"), occupancy(OTHER, "51.2m", 1)[0]) == []
    # the ego at 51.2 m: what waited is drawn, beside its prediction
    prediction, predicted_labels = occupancy(EGO, "51.2m", 1, seed=9)
    (predicted, drawn), (shown, waited) = conv.prediction(prediction)  # the prediction's own cloud first
    late, late_labels = occupancy(EGO, "51.2m", 2, seed=2)
    ((shown_late, now),) = conv.truth(topics.ground_truth(EGO, "51.2m"), late)  # from then on, as it comes
    assert shown == shown_late == topics.EGO_TRUTH_POINTS and predicted == topics.EGO_POINTS
    for raw, labels, stamp in ((drawn, predicted_labels, 1), (waited, early_labels, 1), (now, late_labels, 2)):
        msg = points_of(raw)
        cloud = occupancy_cloud(labels, BENCHMARK_RANGES["51.2m"])
        assert msg.header.frame_id == topics.lidar_frame(EGO) and msg.header.stamp.sec == stamp
        assert msg.width == len(cloud) > 0 and msg.point_step == cloud.itemsize and not msg.is_bigendian
        assert [f.name for f in msg.fields] == list(cloud.dtype.names)
        assert bytes(msg.data) == cloud.tobytes()
    assert [t for t, _ in conv.prediction(occupancy(EGO, "51.2m", 2)[0])] == [topics.EGO_POINTS]  # nothing waits
    assert (
        conv.truth(topics.ground_truth(EGO, "25.6m"), occupancy(EGO, "25.6m", 2)[0]) == []
    )  # another range is not drawn
    assert conv.truth(topics.ground_truth(OTHER, "51.2m"), occupancy(OTHER, "51.2m", 2)[0]) == []  # nor another CAV


def test_waiting_ground_truth_is_bounded():
    conv = RecordingClouds(keep=3)
    for stamp in range(5):
        conv.truth(topics.ground_truth(EGO, "76.8m"), occupancy(EGO, "76.8m", stamp)[0])
    drawn = conv.prediction(occupancy(EGO, "76.8m", 9)[0])
    assert [points_of(raw).header.stamp.sec for _, raw in drawn] == [9, 2, 3, 4]


def test_every_egos_truth_is_drawn_beside_its_own_prediction():
    """Every CAV an ego: each one's truth points go under its namespace, as its prediction does."""
    conv = RecordingClouds()
    for cav in (EGO, OTHER):
        ((shown, raw),) = conv.prediction(occupancy(cav, "51.2m", 1)[0], topics.ego_output(topics.EGO_OCCUPANCY, cav))
        assert shown == topics.ego_output(topics.EGO_POINTS, cav) == f"/cav_{cav}/ego/occupancy/points"
        assert points_of(raw).header.frame_id == topics.lidar_frame(cav)
    for cav in (EGO, OTHER):
        ((shown, raw),) = conv.truth(topics.ground_truth(cav, "51.2m"), occupancy(cav, "51.2m", 2)[0])
        assert shown == topics.ego_output(topics.EGO_TRUTH_POINTS, cav) == f"/cav_{cav}/ego/ground_truth/points"
        assert points_of(raw).header.frame_id == topics.lidar_frame(cav)


@pytest.mark.parametrize("raw", [b"", b"\x00\x01\x00\x00" + bytes(7), bytes(range(256))])
def test_malformed_messages_are_named_not_raised_raw(raw):
    conv = RecordingClouds()
    with pytest.raises(DatasetError, match="/ego/occupancy: not a valid SemanticOccupancy"):
        conv.prediction(raw)
    conv.prediction(occupancy(EGO, "51.2m", 1)[0])
    with pytest.raises(DatasetError, match="occupancy_50m: not a valid SemanticOccupancy"):
        conv.truth(topics.ground_truth(EGO, "51.2m"), raw)


def test_foxglove_layout_shows_prediction_truth_and_the_egos_cameras():
    doc = json.loads(json.dumps(layout(EGO)))  # plain JSON
    config = doc["configById"]
    shown = {t for c in config.values() for t in c.get("topics", {})} | {
        c["imageMode"]["imageTopic"] for c in config.values() if "imageMode" in c
    }
    assert shown == {topics.EGO_POINTS, topics.EGO_TRUTH_POINTS, *(topics.camera_image(EGO, cam) for cam in CAMERAS)}
    assert all(c["followTf"] == topics.lidar_frame(EGO) for k, c in config.items() if k.startswith("3D!"))

    def leaves(tree):
        return [tree] if isinstance(tree, str) else leaves(tree["first"]) + leaves(tree["second"])

    assert sorted(leaves(doc["layout"])) == sorted(config)  # every panel placed once


def test_the_shipped_layout_is_the_generated_one():
    """config/foxglove_layout.json (the demo scene's ego) is what `layout` makes, so it never drifts from the topics."""
    shipped = json.loads(
        (Path(__file__).resolve().parents[3] / "src/co3sop_nodes/config/foxglove_layout.json").read_text()
    )
    ego = int(shipped["configById"]["3D!prediction"]["followTf"].split("/")[0].removeprefix("cav_"))
    assert shipped == json.loads(json.dumps(layout(ego)))
