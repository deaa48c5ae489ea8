"""Bad input to the ego and a stopped or crashed recorder, over real DDS (the test process is a DDS peer)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from ament_index_python.packages import get_package_share_directory
from co3sop_msgs.msg import SemanticOccupancy, VoxelFeatures
from conftest import executable
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.highlevel import AnyReader

from co3sop_nodes.codec import FeatureCodecConfig, encode_features, encode_labels
from co3sop_nodes.geometry import Pose
from co3sop_nodes.grid import BENCHMARK_RANGES
from co3sop_nodes.model.config import preset
from co3sop_nodes.ros.convert import features_to_msg, labels_to_msg

QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)
EGO, OTHER = 1, 7
T0 = 1_700_000_000_000_000_000


@pytest.fixture
def peer():
    rclpy.init()
    node = rclpy.create_node("test_peer")
    yield node
    node.destroy_node()
    rclpy.try_shutdown()


def start(tmp_path: Path, name: str, *argv: str) -> tuple[subprocess.Popen, Path]:
    log = tmp_path / f"{name}.log"
    return subprocess.Popen(list(argv), stdout=open(log, "w"), stderr=subprocess.STDOUT, env=dict(os.environ)), log


def wait_for(log: Path, pattern: str, proc: subprocess.Popen, timeout: float = 120, n: int = 1) -> str:
    deadline = time.monotonic() + timeout
    while len(re.findall(pattern, log.read_text())) < n:
        assert proc.poll() is None, log.read_text()
        assert time.monotonic() < deadline, f"no {n} x '{pattern}' in {timeout} s:\n{log.read_text()}"
        time.sleep(0.1)
    return log.read_text()


def features(agent: int, stamp: int, pose=Pose((10.0, 5.0, 1.8)), grid=None, channels=32) -> VoxelFeatures:
    grid = grid or preset("tiny").feature_grid
    volume = np.random.default_rng(agent).normal(size=(channels, *grid.dims)).astype(np.float32)
    enc = encode_features(volume, np.full(grid.dims, 0.5, np.float32), grid, FeatureCodecConfig("float16"))
    return features_to_msg(enc, stamp_ns=stamp, frame_id=f"cav_{agent}/lidar", agent_id=agent, pose=pose)


def acked(pub) -> None:
    """Every message published so far reached every subscriber (reliable QoS)."""
    assert pub.wait_for_all_acked(rclpy.duration.Duration(seconds=20))


def wait_subscribed(peer, pubs) -> None:
    deadline = time.monotonic() + 60
    while any(p.get_subscription_count() == 0 for p in pubs):
        assert time.monotonic() < deadline, "no subscriber appeared"
        rclpy.spin_once(peer, timeout_sec=0.1)


def test_ego_drops_bad_messages_with_a_reason_and_keeps_going(tmp_path, peer):
    ego, log = start(tmp_path, "ego", executable("ego"), "--ros-args", "-p", f"ego_id:={EGO}", "-p", "max_wait:=0.5",
                     "-p", "max_payload_mb:=4.0", "-p", "publish_points:=false")
    try:
        wait_for(log, "ready:", ego)
        own = peer.create_publisher(VoxelFeatures, f"/cav_{EGO}/voxel_features", QOS)
        other = peer.create_publisher(VoxelFeatures, f"/cav_{OTHER}/voxel_features", QOS)
        wait_subscribed(peer, [own, other])  # the ego finds /cav_7 in the graph
        other.publish(features(OTHER, T0))
        acked(other)
        own.publish(features(EGO, T0))
        wait_for(log, r"published #1, 1 neighbours used", ego)

        stamp = T0 + 100_000_000
        bad = []
        m = features(OTHER, stamp)
        m.values = bytes(m.values)[: len(m.values) // 2]
        bad.append(("payload", m))  # truncated
        m = features(OTHER, stamp)
        m.values = bytes(np.random.default_rng(0).integers(0, 255, len(m.values), dtype=np.uint8))
        bad.append(("payload", m))  # corrupt
        bad.append(("payload", features(OTHER, stamp, grid=BENCHMARK_RANGES["51.2m"].__class__((0.0, 0.0, 0.0), 0.8, (64, 64, 6)))))
        bad.append(("header", features(OTHER, stamp, pose=Pose((float("nan"), 0.0, 0.0)))))
        bad.append(("header", features(OTHER, stamp, pose=Pose((1e9, 0.0, 0.0)))))
        m = features(OTHER, stamp)
        m.values_raw_size = 2**40
        bad.append(("size", m))
        bad.append(("stale", features(OTHER, T0 - 10**9)))
        for _, msg in bad:
            other.publish(msg)
        text = wait_for(log, r"dropped \(", ego, n=len(bad))
        for kind in ("payload", "header", "size", "stale"):
            want = sum(1 for k, _ in bad if k == kind)
            assert len(re.findall(rf"/cav_{OTHER}/voxel_features: dropped \({kind}\)", text)) == want, text
        assert "does not match the model's" in text and "not finite" in text and "more than" in text and "older than" in text

        other.publish(features(OTHER, stamp))
        acked(other)
        own.publish(features(EGO, stamp))
        text = wait_for(log, r"published #2, 1 neighbours used", ego)
        assert ego.poll() is None and "Traceback" not in text
    finally:
        ego.send_signal(signal.SIGINT)
        ego.wait(30)


def occupancy(stamp: int) -> SemanticOccupancy:
    grid = BENCHMARK_RANGES["51.2m"]
    labels = np.zeros(grid.dims, np.uint8)
    labels[: stamp % 200] = 7
    return labels_to_msg(encode_labels(labels, grid, 24), stamp_ns=stamp, frame_id="cav_1/lidar", agent_id=1)


def record(tmp_path, peer, n: int, *extra: str) -> tuple[subprocess.Popen, Path, Path]:
    out = tmp_path / "rec.mcap"
    rec, log = start(tmp_path, "recorder", executable("recorder"), "--out", str(out), "--topics", "/ego/occupancy", *extra)
    pub = peer.create_publisher(SemanticOccupancy, "/ego/occupancy", QOS)
    wait_subscribed(peer, [pub])
    for i in range(n):
        pub.publish(occupancy(T0 + i))
    acked(pub)
    return rec, log, out


def count(path: Path) -> int:
    with AnyReader([path]) as reader:
        return sum(1 for _ in reader.messages())


def test_recorder_finalises_on_sigterm_with_every_message(tmp_path, peer):
    rec, log, out = record(tmp_path, peer, 40)
    rec.send_signal(signal.SIGTERM)
    assert rec.wait(30) == 0, log.read_text()
    assert "finalised" in log.read_text() and "/ego/occupancy 40" in log.read_text()
    assert count(out) == 40


def test_recover_after_the_recorder_is_killed(tmp_path, peer):
    rec, log, out = record(tmp_path, peer, 40, "--chunk-size", "4096", "--flush-period", "0.2")
    time.sleep(1.0)  # a flush period has passed: everything received is on disk
    rec.kill()
    rec.wait(10)
    with pytest.raises(Exception):  # noqa: B017 - no summary, no footer: readers refuse it
        count(out)
    done = subprocess.run([executable("recover"), str(out)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "was damaged" in done.stdout and "40 messages kept" in done.stdout
    assert count(out) == 40


def test_score_and_recover_explain_bad_files(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap at all")
    for tool in ("score", "recover"):
        done = subprocess.run([executable(tool), str(junk)], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and "junk.mcap" in done.stderr and "Traceback" not in done.stderr, done.stderr


@pytest.mark.parametrize("argv, message", [
    (["vehicle"], "vehicle: error: no vehicle id"),
    (["vehicle", "--id", "3", "--ros-args", "-p", "checkpoint:=/nowhere/model.pt"], "/nowhere/model.pt: no such checkpoint"),
    (["vehicle", "--id", "3", "--ros-args", "-p", "modality:=lidar"], "pick a checkpoint trained for it"),
    (["vehicle", "--id", "3", "--ros-args", "-p", "codec.dtype:=float64"], "float64"),
    (["ego"], "ego: error: no ego id"),
    (["demo", "--model", "/nowhere/model.pt"], "--model /nowhere/model.pt: no such checkpoint"),
    (["demo", "--model", "no-such-model"], "no installed checkpoint 'no-such-model.pt'"),
])
def test_nodes_explain_bad_parameters(argv, message):
    done = subprocess.run([executable(argv[0]), *argv[1:]], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_vehicle_takes_the_installed_parameter_file(tmp_path):
    """The shipped YAML (every parameter with its default) loads; -p after it overrides."""
    params = Path(get_package_share_directory("co3sop_nodes"), "config", "vehicle.yaml")
    proc, log = start(tmp_path, "vehicle", executable("vehicle"), "--id", "3", "--ros-args", "--params-file", str(params),
                      "-p", "codec.dtype:=int8", "-p", "codec.selection:=topk", "-p", "codec.topk:=1024")
    try:
        assert "as int8-topk1024-zstd" in wait_for(log, "ready:", proc)
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
