"""Nodes fed faster than they compute stay current, over real DDS: the ego fuses the newest ready frame and the
vehicle encodes the newest complete one, skipping (and counting) the older ones, so latency stays bounded."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import rclpy
from ament_index_python.packages import get_package_share_directory
from executables import executable, exit_code
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import PointCloud2
from test_node_faults import (
    CAMERA,
    EGO,
    LIDAR_CAV,
    OTHER,
    QOS,
    T0,
    features,
    lidar_frame,
    start,
    wait_ready,
    wait_subscribed,
)

from co3sop_msgs.msg import VoxelFeatures
from co3sop_nodes.common import topics

FRAMES = 40
PERIOD_NS = 20_000_000  # 50 Hz: faster than one core fuses, or encodes in float32


def stop(*procs) -> None:
    for proc, _ in procs:
        proc.send_signal(signal.SIGINT)
    for proc, log in procs:
        assert exit_code(proc, log) == 0, log.read_text()


def test_an_ego_fed_faster_than_it_fuses_stays_current_and_counts_what_it_skipped(tmp_path, peer, sup):
    # DDS holds the whole feed: a starved executor must not lose frames, uncounted, to the queue's depth
    params = ("-p", f"ego_id:={EGO}", "-p", "max_wait:=5.0", "-p", f"queue_depth:={FRAMES}")
    ego = start(tmp_path, "ego", executable("ego"), "--ros-args", *params, *CAMERA)
    try:
        wait_ready(sup, "/ego", *ego)
        pubs = {
            agent: peer.create_publisher(VoxelFeatures, topics.voxel_features(agent), QOS) for agent in (EGO, OTHER)
        }
        wait_subscribed(peer, list(pubs.values()))
        sup.wait_subscribed("/ego", topics.voxel_features(OTHER))
        msgs = [(features(a, T0 + k * PERIOD_NS), a) for k in range(FRAMES) for a in (OTHER, EGO)]
        for k in range(FRAMES):  # neighbour first: each own frame can pair as soon as it comes
            for msg, agent in msgs[2 * k : 2 * k + 2]:
                pubs[agent].publish(msg)
            time.sleep(PERIOD_NS / 1e9)
        last = T0 + (FRAMES - 1) * PERIOD_NS
        sup.wait_reports("ego", 1, 120, lambda r: r["stamp"] == str(last))
        reports = sup.reports("ego")
    finally:
        stop(ego)
    fused, skipped = len(reports), int(reports[-1]["skipped"])
    assert fused + skipped == FRAMES and skipped > 0, (fused, skipped)
    assert all(r["neighbours_used"] == "1" for r in reports)  # every fused frame still paired
    # bounded: the last frame is fused within a few frames' compute of the ego receiving it, not after the backlog
    # (timed from its receipt, not the feed's end: beside a loaded core the executor takes queued messages late)
    fuse_s = max(float(r["total_ms"]) for r in reports) / 1e3
    received = dict(x.split(":") for x in reports[-1]["received_wall_ns"].split(","))[str(EGO)]
    assert (int(reports[-1]["published_wall_ns"]) - int(received)) / 1e9 < 3 * fuse_s + 1.0
    log = ego[1].read_text()
    assert "dropped (behind)" in log and log.count("dropped (behind)") < skipped  # logged once per burst


def test_a_vehicle_fed_faster_than_it_encodes_encodes_the_newest_complete_frame(tmp_path, peer, sup):
    model = str(Path(get_package_share_directory("co3sop_nodes"), "checkpoints", "tiny-lidar.pt"))
    # float32: reduced precision encodes a scan in less than the feed's 20 ms on this project's CPUs
    args = ("--ros-args", "-p", f"checkpoint:={model}", "-p", "precision:=float32")
    vehicle = start(tmp_path, "lidar", executable("vehicle"), "--id", str(LIDAR_CAV), *args)
    try:
        wait_ready(sup, topics.vehicle_node(LIDAR_CAV), *vehicle)
        got: list = []
        peer.create_subscription(VoxelFeatures, topics.voxel_features(LIDAR_CAV), got.append, QOS)
        pose_pub = peer.create_publisher(PoseStamped, topics.lidar_pose(LIDAR_CAV), QOS)
        points_pub = peer.create_publisher(PointCloud2, topics.lidar_points(LIDAR_CAV), QOS)
        wait_subscribed(peer, [pose_pub, points_pub])
        frames = [lidar_frame(T0 + k * PERIOD_NS) for k in range(FRAMES)]
        for pose, points in frames:
            pose_pub.publish(pose)
            points_pub.publish(points)
            rclpy.spin_once(peer, timeout_sec=PERIOD_NS / 1e9)
        last = T0 + (FRAMES - 1) * PERIOD_NS
        sup.wait_reports(f"vehicle cav_{LIDAR_CAV}", 1, 120, lambda r: r["stamp"] == str(last))
        reports = sup.reports(f"vehicle cav_{LIDAR_CAV}")
    finally:
        stop(vehicle)
    encoded, skipped = len(reports), int(reports[-1]["skipped"])
    assert encoded + skipped == FRAMES and 0 < encoded < FRAMES, (encoded, skipped)
