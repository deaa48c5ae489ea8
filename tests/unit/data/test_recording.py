"""MCAP recordings: readable by rosbags; recover keeps every complete chunk of a damaged file."""

import os

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.data.bags import typestore
from co3sop_nodes.data.inventory import describe
from co3sop_nodes.data.recording import McapRecorder, recover
from co3sop_nodes.eval.scoring import read_recording, score, score_recording
from co3sop_nodes.messages import RosbagsTypes, occupancy_msg
from co3sop_nodes.v2x.codec import encode_labels
from co3sop_nodes.viz.bev import save_comparison

GRID = BENCHMARK_RANGES["51.2m"]
TYPE = "co3sop_msgs/msg/SemanticOccupancy"


def message(store, agent: int, stamp: int, labels: np.ndarray) -> bytes:
    enc = encode_labels(labels, GRID, 24)
    msg = occupancy_msg(RosbagsTypes(store), enc, stamp_ns=stamp, frame_id=f"cav_{agent}/lidar", agent_id=agent)
    return store.serialize_cdr(msg, TYPE)


def read(path) -> list[tuple[str, int]]:
    with AnyReader([path]) as reader:
        return [(c.topic, t) for c, t, _ in reader.messages()]


def test_recording_round_trip_and_recovery_after_a_crash(tmp_path):
    store = typestore()
    raw = message(store, 1, 5, np.zeros(GRID.dims, np.uint8))
    path = tmp_path / "r.mcap"
    rec = McapRecorder(path, chunk_size=1024)
    for i in range(30):
        rec.write("/ego/occupancy", TYPE, raw, 1000 + i)
    rec.flush()
    rec.write("/ego/occupancy", TYPE, raw, 2000)  # in the open chunk at the "crash"
    rec._file.flush()
    size = path.stat().st_size
    os.truncate(path, size - 3)
    with pytest.raises(Exception):  # noqa: B017 - a file without summary and footer is refused
        read(path)
    result = recover(path)
    assert not result.complete and result.messages == 30 and result.topics == {"/ego/occupancy": 30}
    assert read(path) == [("/ego/occupancy", 1000 + i) for i in range(30)]
    again = recover(path, tmp_path / "copy.mcap")
    assert again.complete and again.messages == 30


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_every_chunk_compression_reads_back_as_written(tmp_path, compression):
    store = typestore()
    labels = np.zeros(GRID.dims, np.uint8)
    labels[:3] = 7
    path = tmp_path / f"{compression}.mcap"
    with McapRecorder(path, chunk_size=4096, compression=compression) as rec:
        for i in range(5):
            rec.write("/ego/occupancy", TYPE, message(store, 1, i, labels), 1000 + i)
    assert read(path) == [("/ego/occupancy", 1000 + i) for i in range(5)]
    assert np.array_equal(next(iter(read_recording(path).predictions.values())), labels)


def test_an_unknown_compression_is_refused_by_name(tmp_path):
    with pytest.raises(DatasetError, match="compression 'gzip'"):
        McapRecorder(tmp_path / "r.mcap", compression="gzip")
    assert not (tmp_path / "r.mcap").exists()


def test_recover_refuses_what_is_not_mcap(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"hello")
    with pytest.raises(DatasetError, match="x.mcap"):
        recover(tmp_path / "x.mcap")
    with pytest.raises(DatasetError, match="no such file"):
        recover(tmp_path / "none.mcap")


def recording(path):
    """Two CAVs' ground truth (10 rows of road) at stamps 1..3 and the ego's predictions of agent 1."""
    store = typestore()
    truth = np.zeros(GRID.dims, np.uint8)
    truth[:10] = 7
    half = truth.copy()
    half[5:10] = 0
    with McapRecorder(path) as rec:
        for stamp in (1, 2, 3):
            rec.write("/cav_1/ground_truth/occupancy_50m", TYPE, message(store, 1, stamp, truth), stamp)
            rec.write("/cav_2/ground_truth/occupancy_50m", TYPE, message(store, 2, stamp, truth), stamp)
        rec.write("/ego/occupancy", TYPE, message(store, 1, 1, truth), 10)  # perfect
        rec.write("/ego/occupancy", TYPE, message(store, 1, 2, half), 11)  # half the road
        rec.write("/ego/occupancy", TYPE, message(store, 1, 9, truth), 12)  # no ground truth
    return path


def test_info_reads_a_recording_with_ground_truth_point_clouds(tmp_path):
    """The recorder also keeps the ground truth as points (/ego/ground_truth/points, PointCloud2): not a grid."""
    store, t = typestore(), typestore().types
    path = tmp_path / "demo.mcap"
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=1), frame_id="cav_1/lidar")
    cloud = t["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=1,
        width=0,
        fields=[],
        is_bigendian=False,
        point_step=0,
        row_step=0,
        data=np.zeros(0, np.uint8),
        is_dense=True,
    )
    truth = np.zeros(GRID.dims, np.uint8)
    with McapRecorder(path) as rec:
        rec.write("/cav_1/ground_truth/occupancy_50m", TYPE, message(store, 1, 1, truth), 1)
        rec.write(
            "/ego/ground_truth/points",
            "sensor_msgs/msg/PointCloud2",
            store.serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2"),
            1,
        )
    assert "| /ego/ground_truth/points | sensor_msgs/msg/PointCloud2 | 1 |" in describe(path)


def test_score_pairs_by_stamp_and_agent_and_counts_missed_frames(tmp_path):
    path = recording(tmp_path / "run.mcap")
    result = score(read_recording(path))
    assert result.range_name == "51.2m" and result.scored == 3  # only the ego's ground truth counts
    assert result.missed == [(1, 3)] and result.unmatched == [(1, 9)]
    # road: 10 + 5 + 0 predicted right of 30 in truth, nothing else predicted as road
    assert result.summary["per_class_iou"]["road"] == pytest.approx(15 / 30)


def test_score_at_another_range_than_the_predictions_is_explained(tmp_path):
    path = recording(tmp_path / "run.mcap")
    with pytest.raises(DatasetError, match="predictions are at 51.2m, not at the range 25.6m"):
        read_recording(path, "25.6m")


def test_info_summarises_a_recording(tmp_path):
    path = recording(tmp_path / "run.mcap")
    text = describe(path)
    assert "MCAP file: 9 messages" in text and "CAVs [1, 2]" in text and "frames" not in text
    assert f"| /ego/occupancy | {TYPE} | 3 |" in text and f"| /cav_2/ground_truth/occupancy_50m | {TYPE} | 3 |" in text
    road = 6 * 10 * GRID.dims[1] * GRID.dims[2]  # two agents' ground truth at three stamps (predictions are not truth)
    assert f"| 7 road | {road} (" in text
    (tmp_path / "bad.mcap").write_bytes(b"hello")
    with pytest.raises(DatasetError, match="bad.mcap: damaged or not a MCAP recording"):
        describe(tmp_path / "bad.mcap")


def test_score_prints_every_class_and_explains_its_conventions(tmp_path, capsys):
    path = recording(tmp_path / "run.mcap")
    assert score_recording(path, pictures=0) == 0
    text = capsys.readouterr().out
    assert "| 13 sky | - |" in text  # absent from truth and prediction: shown, counted as 0 by the Co3SOP means
    assert "co3sop-readme, the mean over all 24 classes" in text and "co3sop-code, the mean over classes 1..23" in text


def test_score_draws_titled_panels_with_a_legend(tmp_path):
    path = recording(tmp_path / "run.mcap")
    assert score_recording(path, tmp_path, pictures=1) == 0
    assert len(list(tmp_path.glob("bev_cav1_*.png"))) == 1
    truth = np.zeros(GRID.dims, np.uint8)
    truth[:10, :, 0] = 7
    pred = truth.copy()
    pred[:5, :, 1] = 10
    texts = save_comparison(truth, pred, tmp_path / "c.png", "cav 1", GRID.voxel_size)
    assert texts == ["cav 1", "ground truth", "prediction", "7 road", "10 vehicle"]  # only the classes shown
