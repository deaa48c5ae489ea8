"""Bad and hostile input to the nodes and a stopped or crashed recorder, over real DDS (the test process is a DDS peer)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import struct
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from ament_index_python.packages import get_package_share_directory
from diagnostic_msgs.msg import DiagnosticArray
from executables import executable, exit_code
from geometry_msgs.msg import PoseStamped, TransformStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from tf2_msgs.msg import TFMessage

from co3sop_msgs.msg import RequestMap, SemanticOccupancy, VoxelFeatures, VoxelScan
from co3sop_nodes.common import topics
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.messages import features_msg, occupancy_msg, point_cloud_msg, request_msg, scan_msg, time_msg
from co3sop_nodes.model.config import preset
from co3sop_nodes.ros.dds import REQUEST_QOS
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.ros.supervisor import Supervisor
from co3sop_nodes.v2x.codec import FeatureCodecConfig, encode_features, encode_labels, encode_request
from co3sop_nodes.v2x.scan import ScanCodecConfig, encode_scan
from co3sop_nodes.viz.cloud import occupancy_cloud

QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)
CAMERA = ("-p", "checkpoint:=tiny")  # the camera model, whose feature grid and inputs these tests send
EGO, OTHER = 1, 7
T0 = 1_700_000_000_000_000_000


def start(tmp_path: Path, name: str, *argv: str) -> tuple[subprocess.Popen, Path]:
    log = tmp_path / f"{name}.log"
    return subprocess.Popen(list(argv), stdout=open(log, "w"), stderr=subprocess.STDOUT, env=dict(os.environ)), log


@contextlib.contextmanager
def running(tmp_path: Path, name: str, *argv: str):
    """start(...) as a context: the process is stopped with SIGINT on the way out and must exit 0."""
    proc, log = start(tmp_path, name, *argv)
    try:
        yield proc, log
    finally:
        proc.send_signal(signal.SIGINT)
        assert exit_code(proc, log) == 0, log.read_text()


def wait_for(log: Path, pattern: str, proc: subprocess.Popen, timeout: float = 120, n: int = 1) -> str:
    deadline = time.monotonic() + timeout
    while len(re.findall(pattern, log.read_text())) < n:
        assert proc.poll() is None, log.read_text()
        assert time.monotonic() < deadline, f"no {n} x '{pattern}' in {timeout} s:\n{log.read_text()}"
        time.sleep(0.1)
    return log.read_text()


def wait_ready(sup: Supervisor, node: str, proc: subprocess.Popen, log: Path, timeout: float = 120) -> None:
    """`node` (fully qualified) is up: a lifecycle node (ego, a vehicle) in state active, the recorder present in the graph."""

    def up() -> bool:
        assert proc.poll() is None, log.read_text()
        if node == "/recorder":
            return "recorder" in sup.node.get_node_names()
        return f"{node}/get_state" in dict(sup.node.get_service_names_and_types()) and sup.state(node) == "active"

    sup.wait(f"{node} up", up, timeout)


def fused(sup: Supervisor, n: int, neighbours: int, timeout: float = 120) -> None:
    """The ego reported its n-th frame on /diagnostics, fused with `neighbours` neighbours."""
    sup.wait_reports(
        "ego", 1, timeout, lambda r: r["frames_published"] == str(n) and r["neighbours_used"] == str(neighbours)
    )


def features(agent: int, stamp: int, pose=Pose((10.0, 5.0, 1.8)), grid=None, channels=32) -> VoxelFeatures:
    grid = grid or preset("tiny").feature_grid
    volume = np.random.default_rng(agent).normal(size=(channels, *grid.dims)).astype(np.float32)
    enc = encode_features(volume, np.full(grid.dims, 0.5, np.float32), grid, FeatureCodecConfig("float16"))
    return features_msg(RCLPY, enc, stamp_ns=stamp, frame_id=f"cav_{agent}/lidar", agent_id=agent, pose=pose)


def acked(pub) -> None:
    """Every message published so far reached every subscriber (reliable QoS)."""
    assert pub.wait_for_all_acked(rclpy.duration.Duration(seconds=20))


def wait_subscribed(peer, pubs) -> None:
    deadline = time.monotonic() + 60
    while any(p.get_subscription_count() == 0 for p in pubs):
        assert time.monotonic() < deadline, "no subscriber appeared"
        rclpy.spin_once(peer, timeout_sec=0.1)


def start_ego(tmp_path: Path, *params: str) -> tuple[subprocess.Popen, Path]:
    """Ego EGO with a short wait for neighbours and a 4 MB payload limit, and `params`."""
    limits = ("-p", f"ego_id:={EGO}", "-p", "max_wait:=0.5", "-p", "max_payload_mb:=4.0")
    return start(tmp_path, "ego", executable("ego"), "--ros-args", *limits, "-p", "publish_points:=false", *params)


def test_a_node_killed_by_a_fatal_signal_logs_every_threads_stack(tmp_path, sup):
    """A crash in native code (here a SIGSEGV from outside) leaves the node's Python stacks in its log, so a report
    says where it died."""
    proc, log = start_ego(tmp_path)
    wait_ready(sup, "/ego", proc, log)
    proc.send_signal(signal.SIGSEGV)
    assert proc.wait(30) == -signal.SIGSEGV
    text = log.read_text()
    assert "Fatal Python error: Segmentation fault" in text, text
    assert "co3sop_nodes/ros/worker.py" in text, text  # the fusion thread's stack
    assert "rclpy/executors.py" in text and "co3sop_nodes/ros/dds.py" in text, text  # the spinning thread's


def test_ego_drops_bad_messages_with_a_reason_and_keeps_going(tmp_path, peer, sup):
    ego, log = start_ego(tmp_path, *CAMERA)
    try:
        wait_ready(sup, "/ego", ego, log)
        own = peer.create_publisher(VoxelFeatures, f"/cav_{EGO}/voxel_features", QOS)
        other = peer.create_publisher(VoxelFeatures, f"/cav_{OTHER}/voxel_features", QOS)
        wait_subscribed(peer, [own, other])  # the ego finds /cav_7 in the graph
        other.publish(features(OTHER, T0))
        acked(other)
        own.publish(features(EGO, T0))
        fused(sup, 1, 1)

        stamp = T0 + 100_000_000
        bad = []
        m = features(OTHER, stamp)
        m.values = bytes(m.values)[: len(m.values) // 2]
        bad.append(("payload", m))  # truncated
        m = features(OTHER, stamp)
        m.values = bytes(np.random.default_rng(0).integers(0, 255, len(m.values), dtype=np.uint8))
        bad.append(("payload", m))  # corrupt
        bad.append(
            (
                "payload",
                features(OTHER, stamp, grid=BENCHMARK_RANGES["51.2m"].__class__((0.0, 0.0, 0.0), 0.8, (64, 64, 6))),
            )
        )
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
        assert (
            "does not match the model's" in text
            and "not finite" in text
            and "more than" in text
            and "older than" in text
        )

        other.publish(features(OTHER, stamp))
        acked(other)
        own.publish(features(EGO, stamp))
        fused(sup, 2, 1)
        assert ego.poll() is None and "Traceback" not in log.read_text()
    finally:
        ego.send_signal(signal.SIGINT)
        exit_code(ego, log)


def test_the_ego_fuses_each_frame_once_and_refuses_stamps_ahead_of_its_clock(tmp_path, peer, sup):
    """A duplicate of its own frame, a replay of one fused, an own frame and a neighbour's stamped in 2038: each
    dropped and counted by reason; the good frames around them are fused, each once, with the neighbour."""
    with running(
        tmp_path,
        "ego",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={EGO}",
        "-p",
        "max_wait:=2.0",
        "-p",
        "publish_points:=false",
        *CAMERA,
    ) as (ego, log):
        wait_ready(sup, "/ego", ego, log)
        own = peer.create_publisher(VoxelFeatures, f"/cav_{EGO}/voxel_features", QOS)
        other = peer.create_publisher(VoxelFeatures, f"/cav_{OTHER}/voxel_features", QOS)
        wait_subscribed(peer, [own, other])
        sup.wait_subscribed("/ego", f"/cav_{OTHER}/voxel_features")
        future = 2_145_916_800 * 10**9  # 2038-01-01
        other.publish(features(OTHER, future))  # a neighbour's clock glitch: never waited on, never blocks
        other.publish(features(OTHER, T0))
        acked(other)
        own.publish(features(EGO, T0))
        own.publish(features(EGO, T0))  # delivered twice
        fused(sup, 1, 1)
        own.publish(features(EGO, T0))  # replayed after it was fused
        own.publish(features(EGO, future))  # an own clock glitch: later frames must not look stale
        acked(own)
        for k in (1, 2):
            other.publish(features(OTHER, T0 + k * 100_000_000))
            acked(other)
            own.publish(features(EGO, T0 + k * 100_000_000))
            fused(sup, k + 1, 1)
        text = wait_for(log, r"dropped \((repeated|future)\)", ego, n=3)
        last = sup.reports("ego")[-1]
        assert len(sup.reports("ego")) == 3 and last["stamp"] == str(T0 + 200_000_000), sup.reports("ego")
        assert int(last["dropped_repeated"]) == 2 and int(last["dropped_future"]) == 2, last
        assert "ahead of this node's clock" in text and "fused already or waits to be" in text


def occupancy(stamp: int) -> SemanticOccupancy:
    grid = BENCHMARK_RANGES["51.2m"]
    labels = np.zeros(grid.dims, np.uint8)
    labels[: stamp % 200] = 7
    return occupancy_msg(RCLPY, encode_labels(labels, grid, 24), stamp_ns=stamp, frame_id="cav_1/lidar", agent_id=1)


def record(tmp_path, peer, n: int, *extra: str) -> tuple[subprocess.Popen, Path, Path]:
    out = tmp_path / "rec.mcap"
    rec, log = start(
        tmp_path, "recorder", executable("recorder"), "--out", str(out), "--topics", "/ego/occupancy", *extra
    )
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
    assert exit_code(rec, log) == 0, log.read_text()
    assert "finalised" in log.read_text() and "/ego/occupancy 40" in log.read_text()
    assert count(out) == 80  # each prediction with the points the recorder draws of it


def test_recover_after_the_recorder_is_killed(tmp_path, peer):
    rec, log, out = record(tmp_path, peer, 40, "--chunk-size", "4096", "--flush-period", "0.2")
    time.sleep(1.0)  # a flush period has passed: everything received is on disk
    rec.kill()
    rec.wait(10)
    with pytest.raises(Exception):  # noqa: B017 - no summary, no footer: readers refuse it
        count(out)
    done = subprocess.run([executable("recover"), str(out)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "was damaged" in done.stdout and "80 messages kept" in done.stdout  # and their points
    assert "/ego/occupancy: 40" in done.stdout and count(out) == 80


def test_score_and_recover_explain_bad_files(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap at all")
    for tool in ("score", "recover"):
        done = subprocess.run([executable(tool), str(junk)], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and "junk.mcap" in done.stderr and "Traceback" not in done.stderr, done.stderr


@pytest.mark.parametrize(
    "argv, message",
    [
        (["vehicle"], "vehicle: error: parameter id is required"),
        (
            ["vehicle", "--id", "3", "--ros-args", "-p", "checkpoint:=/nowhere/model.pt"],
            "/nowhere/model.pt: no such checkpoint",
        ),
        (["vehicle", "--id", "3", "--ros-args", "-p", "modality:=camera"], "pick a checkpoint trained for it"),
        (["vehicle", "--id", "3", "--ros-args", "-p", "codec.dtype:=float64"], "float64"),
        (["vehicle", "--id", "3", "--ros-args", "-p", "codec.level:=99"], "codec.level out of range"),
        (
            ["vehicle", "--id", "3", "--ros-args", "-p", "checkpoint:=tiny", "-p", "send:=scan"],
            "parameter send=scan: tiny is a camera model",
        ),
        (["vehicle", "--id", "3", "--ros-args", "-p", "send:=points"], "send"),
        (["ego"], "ego: error: parameter ego_id is required"),
        (
            ["ego", "--ros-args", "-p", "ego_id:=1", "-p", "max_collaborators:=9"],
            "max_collaborators 9 is above the model's 6",
        ),
        (["ego", "--ros-args", "-p", "ego_id:=1", "-p", "max_wait:=two"], "parameter max_wait"),
        (["demo", "--model", "/nowhere/model.pt"], "--model /nowhere/model.pt: no such checkpoint"),
        (
            ["demo", "--model", "no-such-model"],
            "--model 'no-such-model': neither a checkpoint file nor a shipped model (small, tiny, tiny-lidar, "
            "tiny-lidar-76.8m, tiny-lidar-76.8m-wire, tiny-lidar-wire)",
        ),
        (
            ["ego", "--ros-args", "-p", "ego_id:=1", "-p", "checkpoint:=bogus"],
            "parameter checkpoint 'bogus': neither a checkpoint file",
        ),
        (["ego", "--ros-args", "-p", "ego_id:=1", "-p", "device:=gpu"], "parameter device 'gpu': not a device"),
        (
            ["evaluate", "--model", "bogus", "--data", "."],
            "--model 'bogus': neither a checkpoint file nor a shipped model",
        ),
        (["demo", "--rate", "0"], "demo: error: --rate 0.0: must be above 0"),
        (["demo", "--vehicles", "0"], "demo: error: --vehicles 0: at least 1"),
        (["monitor", "--period", "0"], "monitor: error: --period must be above 0"),
        (
            ["recorder", "--out", "x.mcap", "--flush-period", "0"],
            "recorder: error: --chunk-size must be at least 1 byte, --flush-period above 0",
        ),
        (["recorder", "--out", "x.mcap", "--topics", "(["], "recorder: error: --topics '([': not a regular expression"),
    ],
)
def test_nodes_explain_bad_parameters(argv, message):
    done = subprocess.run([executable(argv[0]), *argv[1:]], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_vehicle_takes_the_installed_parameter_file(tmp_path, sup):
    """The shipped YAML (every parameter with its default) loads; -p after it overrides."""
    params = Path(get_package_share_directory("co3sop_nodes"), "config", "vehicle.yaml")
    proc, log = start(
        tmp_path,
        "vehicle",
        executable("vehicle"),
        "--id",
        "3",
        "--ros-args",
        "--params-file",
        str(params),
        "-p",
        "codec.dtype:=int8",
        "-p",
        "codec.selection:=topk",
        "-p",
        "codec.topk:=1024",
        *CAMERA,
    )
    try:
        wait_ready(sup, topics.vehicle_node(3), proc, log)
        assert "as int8-topk1024-zstd" in log.read_text()
    finally:
        proc.send_signal(signal.SIGINT)
        assert exit_code(proc, log) == 0, log.read_text()


# --- hostile input: malformed CDR, non-finite payloads, silent publishers, crafted checkpoints -------------------

STATIC = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
CAMERA_CAV, LIDAR_CAV = 3, 4
NODES = {
    "ego": "/ego",
    "camera": topics.vehicle_node(CAMERA_CAV),
    "lidar": topics.vehicle_node(LIDAR_CAV),
    "recorder": "/recorder",
}  # process -> node


def scan(agent: int, stamp: int, pose=Pose((10.0, 5.0, 1.8)), grid=None) -> VoxelScan:
    grid = grid or preset("tiny-lidar").grid
    occupancy = np.random.default_rng(agent).random(grid.dims) < 0.01
    enc = encode_scan(occupancy, grid, ScanCodecConfig())
    return scan_msg(RCLPY, enc, stamp_ns=stamp, frame_id=f"cav_{agent}/lidar", agent_id=agent, pose=pose)


def test_ego_encodes_a_neighbours_scan_and_drops_bad_ones_with_a_reason(tmp_path, peer, sup):
    """A LiDAR ego takes a neighbour's VoxelScan (found by type, like features) and runs its model on it; a scan
    that is cut, lies about its size or voxels, is of another grid or pose, or comes where its own features should,
    is dropped by reason, and the ego goes on fusing."""
    lidar = preset("tiny-lidar")
    ego, log = start_ego(tmp_path, "-p", "checkpoint:=tiny-lidar")
    try:
        wait_ready(sup, "/ego", ego, log)
        own = peer.create_publisher(VoxelFeatures, f"/cav_{EGO}/voxel_features", QOS)
        other = peer.create_publisher(VoxelScan, f"/cav_{OTHER}/voxel_scan", QOS)
        wait_subscribed(peer, [own, other])  # the ego finds /cav_7/voxel_scan in the graph
        other.publish(scan(OTHER, T0))
        acked(other)
        own.publish(features(EGO, T0, grid=lidar.feature_grid))
        fused(sup, 1, 1)

        stamp = T0 + 100_000_000
        bad = []
        m = scan(OTHER, stamp)
        m.occupancy = bytes(m.occupancy)[: len(m.occupancy) // 2]
        bad.append(("payload", m))  # truncated
        m = scan(OTHER, stamp)
        m.num_voxels += 1
        bad.append(("payload", m))  # lies about its voxels
        coarser = GridSpec(lidar.grid.origin, 2 * lidar.grid.voxel_size, lidar.grid.dims)
        bad.append(("payload", scan(OTHER, stamp, grid=coarser)))  # as many voxels, of another size
        m = scan(OTHER, stamp)
        m.occupancy_raw_size = 2**40
        bad.append(("size", m))
        bad.append(("header", scan(OTHER, stamp, pose=Pose((float("nan"), 0.0, 0.0)))))
        for _, msg in bad:
            other.publish(msg)
        text = wait_for(log, r"dropped \(", ego, n=len(bad))
        for kind in ("payload", "size", "header"):
            want = sum(1 for k, _ in bad if k == kind)
            assert len(re.findall(rf"/cav_{OTHER}/voxel_scan: dropped \({kind}\)", text)) == want, text
        assert "num_voxels: declares" in text and "grid 256x256x24 @ 0.4 m does not match the model's" in text

        other.publish(scan(OTHER, stamp))
        acked(other)
        own.publish(features(EGO, stamp, grid=lidar.feature_grid))
        fused(sup, 2, 1)
        assert ego.poll() is None and "Traceback" not in log.read_text()
    finally:
        ego.send_signal(signal.SIGINT)
        exit_code(ego, log)


def malformed(msg_type) -> dict[str, bytes]:
    """Raw CDR no node may die of: a valid message cut in half, one whose string length claims 2 GB, random bytes."""
    msg = msg_type()
    if msg_type is TFMessage:
        msg.transforms = [TransformStamped()]
    header = msg.transforms[0].header if msg_type is TFMessage else msg.header
    header.frame_id = "x" * 999  # CDR: uint32 length 1000 (with the terminating NUL), then the characters
    valid = serialize_message(msg)
    at = valid.index(struct.pack("<I", 1000))
    return {
        "truncated": valid[: len(valid) // 2],
        "lying-length": valid[:at] + struct.pack("<I", 0x7FFFFFF0) + valid[at + 4 :],
        "random": np.random.default_rng(len(valid)).bytes(len(valid)),
    }


def diagnostics_of(peer, seen: list) -> object:
    """Collects /diagnostics statuses (raw: the test publishes malformed ones there too)."""

    def on_raw(raw: bytes) -> None:
        try:
            seen.extend(deserialize_message(raw, DiagnosticArray).status)
        except Exception:
            pass

    return peer.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_raw, QOS, raw=True)


def status_values(seen: list, name: str, peer, timeout: float = 60) -> dict[str, str]:
    deadline = time.monotonic() + timeout
    while not any(s.name == name for s in seen):
        assert time.monotonic() < deadline, f"no diagnostics from {name}"
        rclpy.spin_once(peer, timeout_sec=0.1)
    return {kv.key: kv.value for kv in [s for s in seen if s.name == name][-1].values}


def lidar_frame(stamp: int) -> tuple[PoseStamped, PointCloud2]:
    grid = BENCHMARK_RANGES["51.2m"]
    labels = np.zeros(grid.dims, np.uint8)
    labels[100:140, 100:140, 4:8] = 11  # a wall in front of the sensor
    pose = PoseStamped()
    pose.header.stamp = time_msg(RCLPY, stamp)
    pose.header.frame_id = "map"
    pose.pose.orientation.w = 1.0
    return pose, point_cloud_msg(
        RCLPY, occupancy_cloud(labels, grid), stamp_ns=stamp, frame_id=topics.lidar_frame(LIDAR_CAV)
    )


def test_nodes_survive_malformed_cdr_on_every_topic_they_subscribe_to(tmp_path, peer, sup):
    """Raw malformed CDR on each topic of the ego, a camera and a LiDAR vehicle, and the recorder: every node keeps
    running, names the topic and the reason, counts the drops in /diagnostics and still does its job."""
    lidar_model = str(Path(get_package_share_directory("co3sop_nodes"), "checkpoints", "tiny-lidar.pt"))
    procs = {
        "ego": start(
            tmp_path,
            "ego",
            executable("ego"),
            "--ros-args",
            "-p",
            f"ego_id:={EGO}",
            "-p",
            "max_wait:=0.5",
            "-p",
            "publish_points:=false",
            *CAMERA,
        ),
        "camera": start(tmp_path, "camera", executable("vehicle"), "--id", str(CAMERA_CAV), "--ros-args", *CAMERA),
        "lidar": start(
            tmp_path,
            "lidar",
            executable("vehicle"),
            "--id",
            str(LIDAR_CAV),
            "--ros-args",
            "-p",
            f"checkpoint:={lidar_model}",
        ),
        "recorder": start(tmp_path, "recorder", executable("recorder"), "--out", str(tmp_path / "rec.mcap")),
    }
    try:
        for name, (proc, log) in procs.items():
            wait_ready(sup, NODES[name], proc, log)
        targets = {  # topic -> (type, QoS, the node that must name it)
            topics.voxel_features(EGO): (VoxelFeatures, QOS, "ego"),
            topics.voxel_features(OTHER): (VoxelFeatures, QOS, "ego"),
            topics.TF_STATIC: (TFMessage, STATIC, "camera"),
            topics.lidar_pose(CAMERA_CAV): (PoseStamped, QOS, "camera"),
            **{
                t: (m, QOS, "camera")
                for cam in ("camera0", "camera3")
                for t, m in (
                    (topics.camera_image(CAMERA_CAV, cam), Image),
                    (topics.camera_info(CAMERA_CAV, cam), CameraInfo),
                )
            },
            topics.lidar_pose(LIDAR_CAV): (PoseStamped, QOS, "lidar"),
            topics.lidar_points(LIDAR_CAV): (PointCloud2, QOS, "lidar"),
            topics.EGO_OCCUPANCY: (SemanticOccupancy, QOS, "recorder"),
            topics.ground_truth(EGO, "51.2m"): (SemanticOccupancy, QOS, "recorder"),
            topics.DIAGNOSTICS: (DiagnosticArray, QOS, "recorder"),
        }
        pubs = {t: peer.create_publisher(m, t, q) for t, (m, q, _) in targets.items()}
        seen: list = []
        diagnostics_of(peer, seen)
        wait_subscribed(peer, list(pubs.values()))
        for topic, pub in pubs.items():
            for raw in malformed(targets[topic][0]).values():
                pub.publish(raw)
            acked(pub)
        for topic, (_, _, node) in targets.items():
            if node != "recorder":  # the recorder stores bytes as they came, never deserialising
                wait_for(procs[node][1], rf"{re.escape(topic)}: dropped \(malformed\)", procs[node][0])
        text = procs["camera"][1].read_text()
        assert "not a valid Image" in text and "not a valid CameraInfo" in text and "not a valid TFMessage" in text, (
            text
        )

        # still working, and the drops are counted where operators look
        pubs[topics.voxel_features(OTHER)].publish(features(OTHER, T0))
        acked(pubs[topics.voxel_features(OTHER)])
        pubs[topics.voxel_features(EGO)].publish(features(EGO, T0))
        fused(sup, 1, 1)
        assert status_values(seen, "ego", peer)["dropped_malformed"] == "6"
        for msg, topic in zip(lidar_frame(T0), (topics.lidar_pose(LIDAR_CAV), topics.lidar_points(LIDAR_CAV))):
            pubs[topic].publish(msg)
        values = status_values(seen, f"vehicle cav_{LIDAR_CAV}", peer)
        assert values["frames_published"] == "1" and values["dropped_malformed"] == "9", (
            values
        )  # /tf_static, pose, points
        pubs[topics.EGO_OCCUPANCY].publish(occupancy(T0))
        acked(pubs[topics.EGO_OCCUPANCY])
        for name, (proc, log) in procs.items():
            assert proc.poll() is None and "Traceback" not in log.read_text(), f"{name}:\n{log.read_text()}"
    finally:
        for proc, _ in procs.values():
            proc.send_signal(signal.SIGINT)
        for name, (proc, log) in procs.items():
            assert exit_code(proc, log) == 0, f"{name}:\n{log.read_text()}"
    assert count(tmp_path / "rec.mcap") >= 1 + 3 * 3  # the malformed bytes are recorded as they came


NON_FINITE = {  # field -> how a faulty sender spoils it (after encoding, so the codec's own checks are bypassed)
    "values": ("float32", lambda m: setattr(m, "values", _spoil(m.values, np.float32))),
    "confidence": ("float16", lambda m: setattr(m, "confidence", _spoil(m.confidence, np.float16))),
    "quant_scale": ("int8", lambda m: setattr(m, "quant_scale", [float("nan"), *list(m.quant_scale)[1:]])),
    "quant_offset": ("int8", lambda m: setattr(m, "quant_offset", [*list(m.quant_offset)[:-1], float("inf")])),
}


def _spoil(payload, dtype) -> bytes:
    import zstandard

    array = np.frombuffer(zstandard.ZstdDecompressor().decompress(bytes(payload)), dtype).copy()
    array[len(array) // 3] = np.nan
    return zstandard.ZstdCompressor(write_checksum=True, write_content_size=True).compress(array.tobytes())


def spoiled(field: str, stamp: int) -> VoxelFeatures:
    dtype, spoil = NON_FINITE[field]
    grid = preset("tiny").feature_grid
    volume = np.random.default_rng(OTHER).normal(size=(32, *grid.dims)).astype(np.float32)
    # plain zstd: its payload is the values in order, spoiled in place (the codec's tests spoil shuffle-zstd's too)
    enc = encode_features(volume, np.full(grid.dims, 0.5, np.float32), grid, FeatureCodecConfig(dtype, codec="zstd"))
    msg = features_msg(
        RCLPY, enc, stamp_ns=stamp, frame_id=f"cav_{OTHER}/lidar", agent_id=OTHER, pose=Pose((10.0, 5.0, 1.8))
    )
    spoil(msg)
    return msg


def test_ego_drops_non_finite_payloads_and_waits_only_for_neighbours_that_speak(tmp_path, peer, sup):
    """NaN or inf in any payload field is dropped with the field named; a neighbour whose publisher exists but has not
    sent within neighbour_timeout of the ego's first frame is no longer waited for (it would cost every frame max_wait)."""
    ego, log = start(
        tmp_path,
        "ego",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={EGO}",
        "-p",
        "max_wait:=6.0",
        "-p",
        "neighbour_timeout:=1.0",
        "-p",
        "publish_points:=false",
        *CAMERA,
    )
    try:
        wait_ready(sup, "/ego", ego, log)
        own = peer.create_publisher(VoxelFeatures, topics.voxel_features(EGO), QOS)
        other = peer.create_publisher(VoxelFeatures, topics.voxel_features(OTHER), QOS)
        silent = peer.create_publisher(VoxelFeatures, topics.voxel_features(9), QOS)  # exists, never sends
        wait_subscribed(peer, [own, other, silent])
        for field in NON_FINITE:
            other.publish(spoiled(field, T0))
        text = wait_for(log, r"dropped \(non_finite\)", ego, n=len(NON_FINITE))
        for field in NON_FINITE:
            assert re.search(
                rf"/cav_{OTHER}/voxel_features: dropped \(non_finite\): {field}: 1 NaN or infinite", text
            ), text

        # neither cav 7 (only bad messages) nor the silent cav 9 has spoken: the first frame waits for them only until
        # neighbour_timeout (1 s) after it arrived, not max_wait (6 s)
        t0 = time.monotonic()
        own.publish(features(EGO, T0))
        fused(sup, 1, 0)
        assert time.monotonic() - t0 < 3.0, "the ego waited for a neighbour that never sent (max_wait is 6 s)"

        other.publish(features(OTHER, T0 + 100_000_000))  # speaks again: live, waited for, fused
        acked(other)
        own.publish(features(EGO, T0 + 100_000_000))
        fused(sup, 2, 1)
        assert ego.poll() is None and "Traceback" not in log.read_text()
    finally:
        ego.send_signal(signal.SIGINT)
        exit_code(ego, log)


@pytest.fixture
def crafted(tmp_path) -> tuple[Path, Path]:
    """A checkpoint whose unpickling would create a marker file."""
    import torch

    marker = tmp_path / "code-ran"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    path = tmp_path / "crafted.pt"
    torch.save({"config": {}, "model": {}, "meta": Payload()}, path)
    return path, marker


@pytest.mark.parametrize(
    "argv",
    [
        ["vehicle", "--id", "3", "--ros-args", "-p", "checkpoint:={model}"],
        ["ego", "--ros-args", "-p", "ego_id:=1", "-p", "checkpoint:={model}"],
        ["evaluate", "--model", "{model}", "--data", "{data}"],
        ["train", "--data", "{data}", "--stage", "fusion", "--init", "{model}", "--out", "{out}"],
        ["demo", "--model", "{model}", "--out", "{out}"],
    ],
    ids=lambda argv: argv[0],
)
def test_no_entry_point_runs_code_from_a_checkpoint(crafted, tmp_path, argv):
    model, marker = crafted
    args = [a.format(model=model, data=tmp_path, out=tmp_path / "out") for a in argv]
    done = subprocess.run([executable(args[0]), *args[1:]], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "crafted.pt: refused" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not marker.exists()


# --- QoS: drivers that publish best effort ----------------------------------------------------------------------

BEST_EFFORT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)


def test_best_effort_sensors_are_encoded_and_best_effort_topics_recorded(tmp_path, peer, sup):
    """A LiDAR driver and a ground-truth source that publish best effort (as most drivers do): the vehicle and the
    recorder subscribe with the QoS offered, so they match and get the messages (a reliable subscription would not
    match a best-effort publisher at all). The vehicle and the ego take `features_reliability:=best_effort` for the
    features (a lossy V2X link): the vehicle offers best effort, and the ego subscribes best effort to it."""
    lidar_model = str(Path(get_package_share_directory("co3sop_nodes"), "checkpoints", "tiny-lidar.pt"))
    truth_topic = topics.ground_truth(LIDAR_CAV, "51.2m")
    best_effort = ["-p", "features_reliability:=best_effort"]
    features = topics.voxel_features(LIDAR_CAV)
    procs = {
        "lidar": start(
            tmp_path,
            "lidar",
            executable("vehicle"),
            "--id",
            str(LIDAR_CAV),
            "--ros-args",
            "-p",
            f"checkpoint:={lidar_model}",
            *best_effort,
        ),
        "recorder": start(
            tmp_path,
            "recorder",
            executable("recorder"),
            "--out",
            str(tmp_path / "rec.mcap"),
            "--topics",
            re.escape(truth_topic),
        ),
        "ego": start(
            tmp_path,
            "ego",
            executable("ego"),
            "--ros-args",
            "-p",
            f"ego_id:={EGO}",
            "-p",
            f"checkpoint:={lidar_model}",
            *best_effort,
        ),
    }
    try:
        for name, (proc, log) in procs.items():
            wait_ready(sup, NODES[name], proc, log)
        sup.wait_published(NODES["lidar"], features)  # ready, and seen in the graph: the view may lag
        assert [i.qos_profile.reliability for i in sup.node.get_publishers_info_by_topic(features)] == [
            ReliabilityPolicy.BEST_EFFORT
        ]
        sup.wait_subscribed("/ego", features)
        deadline = time.monotonic() + 30  # the peer is a participant of its own: it learns of the ego on its own time
        while not (
            requested := {
                i.qos_profile.reliability
                for i in peer.get_subscriptions_info_by_topic(features)
                if i.node_name == "ego"
            }
        ):
            assert time.monotonic() < deadline, "the peer never saw the ego's subscription"
            time.sleep(0.1)
        assert requested == {ReliabilityPolicy.BEST_EFFORT}
        got: list = []
        peer.create_subscription(VoxelFeatures, features, got.append, BEST_EFFORT)
        pose_pub = peer.create_publisher(PoseStamped, topics.lidar_pose(LIDAR_CAV), BEST_EFFORT)
        points_pub = peer.create_publisher(PointCloud2, topics.lidar_points(LIDAR_CAV), BEST_EFFORT)
        truth_pub = peer.create_publisher(SemanticOccupancy, truth_topic, BEST_EFFORT)
        wait_subscribed(peer, [pose_pub, points_pub, truth_pub])
        wait_for(
            procs["recorder"][1],
            rf"recording {re.escape(truth_topic)} \(co3sop_msgs/msg/SemanticOccupancy, best_effort\)",
            procs["recorder"][0],
        )
        deadline = time.monotonic() + 60
        stamp = T0
        while not got:  # best effort may lose a message: send frames until one is encoded
            assert time.monotonic() < deadline, procs["lidar"][1].read_text()
            for msg, pub in zip(lidar_frame(stamp), (pose_pub, points_pub)):
                pub.publish(msg)
            stamp += 100_000_000
            end = time.monotonic() + 1.0
            while not got and time.monotonic() < end:
                rclpy.spin_once(peer, timeout_sec=0.1)
        assert got[0].agent_id == LIDAR_CAV
        for _ in range(
            10
        ):  # best effort drops what comes before the receiving side has matched the sender: keep sending
            truth_pub.publish(occupancy(stamp))
            stamp += 100_000_000
            time.sleep(0.2)
    finally:
        for proc, _ in procs.values():
            proc.send_signal(signal.SIGINT)
        for proc, log in procs.values():
            assert exit_code(proc, log) == 0, log.read_text()
    with AnyReader([tmp_path / "rec.mcap"]) as reader:
        assert sum(c.msgcount for c in reader.connections if c.topic == truth_topic) >= 1


# --- parameters: described, checked, changed at run time ---------------------------------------------------------


def call(peer, future):
    rclpy.spin_until_future_complete(peer, future, timeout_sec=30)
    assert future.done(), "no answer from the parameter service"
    return future.result()


def lidar_features(peer, proc: subprocess.Popen, log: Path) -> list[VoxelFeatures]:
    """What the LiDAR vehicle publishes for one frame sent to it."""
    got: list = []
    peer.create_subscription(VoxelFeatures, topics.voxel_features(LIDAR_CAV), got.append, QOS)
    pubs = [
        peer.create_publisher(m, t, QOS)
        for m, t in ((PoseStamped, topics.lidar_pose(LIDAR_CAV)), (PointCloud2, topics.lidar_points(LIDAR_CAV)))
    ]
    wait_subscribed(peer, pubs)
    for msg, pub in zip(lidar_frame(T0), pubs):
        pub.publish(msg)
    deadline = time.monotonic() + 60
    while not got:
        assert time.monotonic() < deadline and proc.poll() is None, log.read_text()
        rclpy.spin_once(peer, timeout_sec=0.1)
    return got


def test_parameters_are_described_and_checked_when_set_at_run_time(tmp_path, peer, sup):
    """`ros2 param describe` shows descriptions, ranges and read-only flags; `ros2 param set` takes a run-time
    value (the next frame is encoded with it), refuses a bad one with a reason and refuses what needs a restart."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    from co3sop_nodes.ros import ego as ego_node

    lidar_model = str(Path(get_package_share_directory("co3sop_nodes"), "checkpoints", "tiny-lidar.pt"))
    procs = {
        "ego": start(tmp_path, "ego", executable("ego"), "--ros-args", "-p", f"ego_id:={EGO}", *CAMERA),
        "lidar": start(
            tmp_path,
            "lidar",
            executable("vehicle"),
            "--id",
            str(LIDAR_CAV),
            "--ros-args",
            "-p",
            f"checkpoint:={lidar_model}",
        ),
    }
    try:
        for name, (proc, log) in procs.items():
            wait_ready(sup, NODES[name], proc, log)
        ego = AsyncParameterClient(peer, "ego")
        vehicle = AsyncParameterClient(peer, topics.vehicle_node(LIDAR_CAV))
        assert ego.wait_for_services(30) and vehicle.wait_for_services(30)
        listed = set(call(peer, ego.list_parameters()).result.names)
        assert {p.name for p in ego_node.PARAMS} <= listed
        tolerance, checkpoint = call(peer, ego.describe_parameters(["tolerance", "checkpoint"])).descriptors
        assert tolerance.description and not tolerance.read_only and tolerance.floating_point_range[0].to_value == 10.0
        assert checkpoint.read_only
        assert (
            call(peer, vehicle.describe_parameters(["codec.dtype"]))
            .descriptors[0]
            .additional_constraints.startswith("one of")
        )

        def set_(client, name, value):
            return call(peer, client.set_parameters([Parameter(name, value=value)])).results[0]

        assert set_(ego, "max_collaborators", 2).successful
        assert call(peer, ego.get_parameters(["max_collaborators"])).values[0].integer_value == 2
        refused = set_(ego, "max_collaborators", 9)
        assert not refused.successful and "above the model's 6" in refused.reason
        assert not set_(ego, "tolerance", -1.0).successful
        assert "read-only" in set_(ego, "checkpoint", "/other.pt").reason
        refused = set_(vehicle, "codec.dtype", "int9")
        assert not refused.successful and "int9" in refused.reason
        # values the descriptor allows but this model cannot use: refused when set, not frame after frame
        refused = set_(vehicle, "codec.rank", 33)
        assert not refused.successful and "more components than the 32 feature channels" in refused.reason
        assert set_(vehicle, "codec.selection", "topk").successful
        refused = set_(vehicle, "codec.max_bytes", 16)
        assert not refused.successful and "even an empty selection takes" in refused.reason
        assert set_(vehicle, "codec.selection", "dense").successful
        assert set_(vehicle, "request_timeout", 2.0).successful  # a run-time value outside the codec

        # request maps subscribed with selection request only: an ego makes its maps for subscribers alone
        node = topics.vehicle_node(LIDAR_CAV)
        sup.wait_published("/ego", topics.EGO_REQUEST)
        time.sleep(1.5)  # three of the vehicle's discovery periods
        assert not sup.subscribes(node, topics.EGO_REQUEST)
        assert set_(vehicle, "codec.selection", "request").successful
        sup.wait_subscribed(node, topics.EGO_REQUEST, 30)
        assert set_(vehicle, "codec.selection", "dense").successful
        sup.wait("the request map released", lambda: not sup.subscribes(node, topics.EGO_REQUEST), 30)

        # a changed codec is used from the next frame on
        assert set_(vehicle, "codec.dtype", "int8").successful
        got = lidar_features(peer, *procs["lidar"])
        assert got[0].dtype == "int8"
    finally:
        for proc, _ in procs.values():
            proc.send_signal(signal.SIGINT)
        for proc, log in procs.values():
            assert exit_code(proc, log) == 0, log.read_text()


def runtime_values(param) -> tuple[list, object]:
    """Every kind of value a run-time parameter's descriptor allows (its bounds, each choice, both booleans), and one
    it does not."""
    if param.type is bool:
        return [True, False], "yes"
    if param.choices:
        return list(param.choices), "bogus"
    if param.range:
        lo, hi = param.range
        return [param.type(lo), param.type(hi)], param.type(hi) + 1
    return [param.default], 3.5


def test_every_run_time_parameter_at_its_bounds_never_ends_a_node(tmp_path, peer, sup):
    """Each run-time parameter of the ego and a vehicle set to every value its descriptor allows and to one it does
    not: each is taken or refused with a reason, the nodes live on, and with the defaults back they still produce
    frames."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    from co3sop_nodes.ros import ego as ego_node
    from co3sop_nodes.ros import vehicle as vehicle_node

    lidar_model = str(Path(get_package_share_directory("co3sop_nodes"), "checkpoints", "tiny-lidar.pt"))
    procs = {
        "ego": start(
            tmp_path,
            "ego",
            executable("ego"),
            "--ros-args",
            "-p",
            f"ego_id:={EGO}",
            "-p",
            f"checkpoint:={lidar_model}",
            "-p",
            "max_wait:=0.5",
        ),
        "lidar": start(
            tmp_path,
            "lidar",
            executable("vehicle"),
            "--id",
            str(LIDAR_CAV),
            "--ros-args",
            "-p",
            f"checkpoint:={lidar_model}",
        ),
    }
    try:
        for name, (proc, log) in procs.items():
            wait_ready(sup, NODES[name], proc, log)
        for name, params in (("ego", ego_node.PARAMS), ("lidar", vehicle_node.PARAMS)):
            client = AsyncParameterClient(peer, NODES[name])
            assert client.wait_for_services(30)
            initial = {p.name: p.default for p in params if p.runtime}
            for param in (p for p in params if p.runtime):
                good, bad = runtime_values(param)
                for value, allowed in [*((v, True) for v in good), (bad, False)]:
                    result = call(peer, client.set_parameters([Parameter(param.name, value=value)])).results[0]
                    assert result.successful or result.reason, (param.name, value)  # refused only with a reason
                    assert allowed or not result.successful, (param.name, value)
                    assert procs[name][0].poll() is None, procs[name][1].read_text()
            back = call(
                peer, client.set_parameters_atomically([Parameter(n, value=v) for n, v in initial.items()])
            ).result
            assert back.successful, back.reason
        # both still work: the vehicle encodes a LiDAR frame, the ego fuses its own frame with a neighbour's
        sup.wait_subscribed("/ego", topics.voxel_features(LIDAR_CAV))  # before the vehicle's frame goes out
        got = lidar_features(peer, *procs["lidar"])
        own = peer.create_publisher(VoxelFeatures, topics.voxel_features(EGO), QOS)
        wait_subscribed(peer, [own])
        lidar_grid = preset("tiny-lidar").feature_grid
        own.publish(features(EGO, got[0].header.stamp.sec * 10**9 + got[0].header.stamp.nanosec, grid=lidar_grid))
        fused(sup, 1, 1)
    finally:
        for proc, _ in procs.values():
            proc.send_signal(signal.SIGINT)
        for proc, log in procs.values():
            assert exit_code(proc, log) == 0, log.read_text()


def request_map(ego: int, stamp: int, x: float, fill: float) -> RequestMap:
    grid = preset("tiny-lidar").feature_grid
    return request_msg(
        RCLPY,
        encode_request(np.full(grid.dims, fill, np.float32), grid),
        stamp_ns=stamp,
        frame_id=f"cav_{ego}/lidar",
        agent_id=ego,
        pose=Pose((x, 0.0, 1.8)),
    )


def test_request_maps_are_bound_to_one_topic_refused_from_afar_and_bounded(tmp_path, peer, sup):
    """A spoofed request map claiming an ego's id from another topic, one from an ego far beyond comm_range and a
    flood of ids: each refusal counted by kind, the real ego still answered, and at most max_egos answers a frame."""
    lidar_model = str(Path(get_package_share_directory("co3sop_nodes"), "checkpoints", "tiny-lidar.pt"))
    with running(
        tmp_path,
        "lidar",
        executable("vehicle"),
        "--id",
        str(LIDAR_CAV),
        "--ros-args",
        "-p",
        f"checkpoint:={lidar_model}",
        "-p",
        "codec.selection:=request",
        "-p",
        "request_timeout:=60.0",
        "-p",
        "max_egos:=2",
    ) as (vehicle, log):
        wait_ready(sup, NODES["lidar"], vehicle, log)
        got: list = []
        peer.create_subscription(VoxelFeatures, topics.voxel_features(LIDAR_CAV), got.append, QOS)
        pubs = [
            peer.create_publisher(m, t, QOS)
            for m, t in ((PoseStamped, topics.lidar_pose(LIDAR_CAV)), (PointCloud2, topics.lidar_points(LIDAR_CAV)))
        ]
        wait_subscribed(peer, pubs)
        for msg, pub in zip(lidar_frame(T0), pubs):  # a first frame: the vehicle knows where it is
            pub.publish(msg)
        sup.wait_reports(f"vehicle cav_{LIDAR_CAV}", 1, 60)
        real = peer.create_publisher(RequestMap, topics.EGO_REQUEST, REQUEST_QOS)
        spoof = peer.create_publisher(RequestMap, "/spoof/request_map", REQUEST_QOS)
        far = peer.create_publisher(RequestMap, "/far/request_map", REQUEST_QOS)
        flood = peer.create_publisher(RequestMap, "/flood/request_map", REQUEST_QOS)
        sup.wait(
            "the vehicle to subscribe to every request topic",
            lambda: all(
                sup.subscribes(NODES["lidar"], t)
                for t in (topics.EGO_REQUEST, "/spoof/request_map", "/far/request_map", "/flood/request_map")
            ),
            30,
        )
        real.publish(request_map(EGO, T0, 10.0, 1.0))
        acked(real)
        spoof.publish(request_map(EGO, T0, 10.0, 0.0))  # claims the real ego's id, asks for nothing
        far.publish(request_map(OTHER, T0, 5000.0, 1.0))  # 5 km away
        acked(far)
        for fake in range(100, 400):  # many ids, one topic: memory and answers stay bounded
            flood.publish(request_map(fake, T0, 20.0, 1.0))
            acked(flood)  # each taken before the next (a request topic keeps only its newest message)
        acked(spoof)
        got.clear()
        for msg, pub in zip(lidar_frame(T0 + 100_000_000), pubs):
            pub.publish(msg)
        report = sup.wait_reports(f"vehicle cav_{LIDAR_CAV}", 2, 60)[-1]
        deadline = time.monotonic() + 10
        while len(got) < 2 and time.monotonic() < deadline:
            rclpy.spin_once(peer, timeout_sec=0.1)
        recipients = dict(pair.split(":") for pair in report["recipients"].split(","))
        assert len(recipients) == 2 and str(EGO) in recipients, report  # the nearest two: the real ego at 10 m first
        assert int(report["dropped_request_topic"]) == 1 and int(report["dropped_request_range"]) == 1, report
        mine = next(m for m in got if m.recipient_id == EGO)
        assert mine.num_voxels > 0  # answered as the real ego asked, not emptied by the spoof
        assert vehicle.poll() is None


def test_an_id_squatter_neither_locks_the_vehicle_out_nor_outlives_its_publisher(tmp_path, peer, sup):
    with running(
        tmp_path,
        "ego",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={EGO}",
        "-p",
        "max_wait:=2.0",
        "-p",
        "publish_points:=false",
        *CAMERA,
    ) as (ego, log):
        wait_ready(sup, "/ego", ego, log)
        own = peer.create_publisher(VoxelFeatures, topics.voxel_features(EGO), QOS)
        squatter = peer.create_publisher(VoxelFeatures, "/squat/voxel_features", QOS)
        wait_subscribed(peer, [own, squatter])
        sup.wait_subscribed("/ego", "/squat/voxel_features")
        squatter.publish(features(OTHER, T0 - 10**9))  # claims the real vehicle's id first
        acked(squatter)
        real = peer.create_publisher(
            VoxelFeatures, topics.voxel_features(OTHER), QOS
        )  # the vehicle in its own namespace
        wait_subscribed(peer, [real])
        sup.wait_subscribed("/ego", topics.voxel_features(OTHER))
        real.publish(features(OTHER, T0))
        acked(real)
        own.publish(features(EGO, T0))
        fused(sup, 1, 1)
        assert f"vehicle {OTHER} now on {topics.voxel_features(OTHER)}" in log.read_text()
        # a second squatter on another name: refused while the vehicle's topic has a publisher ...
        other_name = peer.create_publisher(VoxelFeatures, "/elsewhere/voxel_features", QOS)
        wait_subscribed(peer, [other_name])
        sup.wait_subscribed("/ego", "/elsewhere/voxel_features")
        other_name.publish(features(OTHER, T0 + 100_000_000))
        wait_for(log, "already published on", ego)
        # ... and takes the id once that publisher is gone (the vehicle restarted under another name, say)
        peer.destroy_publisher(real)
        sup.wait(
            "the vehicle's publisher to leave the graph",
            lambda: sup.node.count_publishers(topics.voxel_features(OTHER)) == 0,
            30,
        )
        other_name.publish(features(OTHER, T0 + 200_000_000))
        acked(other_name)
        own.publish(features(EGO, T0 + 200_000_000))
        fused(sup, 2, 1)
        assert ego.poll() is None


def test_a_flood_of_topics_is_subscribed_up_to_a_bound_and_departed_ones_make_room(tmp_path, peer, sup):
    with running(
        tmp_path,
        "ego",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={EGO}",
        "-p",
        "max_topics:=8",
        "-p",
        "discovery_period:=0.1",
        *CAMERA,
    ) as (ego, log):
        wait_ready(sup, "/ego", ego, log)
        flood = [peer.create_publisher(VoxelFeatures, f"/flood_{i}/voxel_features", QOS) for i in range(12)]
        wait_for(log, r"dropped \(topics\)", ego)
        subscribed = [p.topic_name for p in flood if sup.subscribes("/ego", p.topic_name)]
        assert len(subscribed) == 7  # 8 with the ego's own
        for pub in flood:
            peer.destroy_publisher(pub)
        peer.create_publisher(VoxelFeatures, "/late/voxel_features", QOS)
        sup.wait_subscribed("/ego", "/late/voxel_features")  # departed topics were released to make room ...

        def held() -> list[str]:  # ... those the ego saw depart by then (the graph's view of it may lag)
            return [t for t in subscribed if sup.subscribes("/ego", t)]

        sup.wait("a departed topic released", lambda: len(held()) < len(subscribed), 30)
        assert len(held()) + 2 <= 8  # with its own and /late: within max_topics
        assert ego.poll() is None
