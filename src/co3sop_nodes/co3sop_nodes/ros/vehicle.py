"""`vehicle`: one CAV's encoder: its sensors -> the model's vehicle half -> compressed voxel features over DDS.

    ros2 run co3sop_nodes vehicle --id 3 [--ros-args --params-file vehicle.yaml -p codec.dtype:=int8]

Runs in the namespace /cav_<id> (unless --ros-args -r __ns:=... says
otherwise; its topics are relative to it, so remapping works), subscribes to
camera0..3/image_raw + camera_info and lidar/pose (or lidar/points with a
LiDAR checkpoint) and the camera mounts on /tf_static; groups each frame by
its header stamp, runs the vehicle half of the checkpoint (default: the
shipped tiny-lidar), encodes the feature volume and confidence with the codec
parameters and publishes co3sop_msgs/VoxelFeatures on voxel_features
(reliable); with `send: scan` (LiDAR checkpoints) it publishes its voxelised
scan instead, co3sop_msgs/VoxelScan on voxel_scan, for each ego's copy of the
model to encode; plus its per-frame timings on /diagnostics. Frames are encoded on
a thread of their own (worker.py); a vehicle slower than its sensors encodes
the newest complete frame and skips older ones (counted as `skipped`). A
lifecycle node (ros/lifecycle.py). Parameters: see config/vehicle.yaml.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import fields, replace

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from tf2_msgs.msg import TFMessage

from co3sop_msgs.msg import RequestMap, VoxelFeatures, VoxelScan
from co3sop_nodes.common import topics
from co3sop_nodes.common.allocation import reserve_memory
from co3sop_nodes.common.errors import Co3sopError, CodecError
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.common.transforms import StaticTransforms
from co3sop_nodes.inference.checkpoint import load_graph_model, resolve_checkpoint
from co3sop_nodes.inference.inputs import sensor_inputs, to_batch
from co3sop_nodes.inference.outputs import code_id, encode_output
from co3sop_nodes.inference.pace import warm_up
from co3sop_nodes.inference.predict import compile_kernels
from co3sop_nodes.messages import (
    diagnostics_msg,
    features_msg,
    intrinsics_of,
    pose_of,
    request_of,
    rgb_of,
    scan_msg,
    stamp_ns,
    transforms_of,
    xyz_of,
)
from co3sop_nodes.model.path import PRECISIONS
from co3sop_nodes.ros.dds import (
    DIAGNOSTICS_QOS,
    RELIABILITIES,
    REQUEST_QOS,
    DropLog,
    SensorSubscriptions,
    features_qos,
    spin_node,
    subscribe_foreign,
)
from co3sop_nodes.ros.lifecycle import AUTOSTART, ManagedNode
from co3sop_nodes.ros.links import publish_links
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.ros.params import Param, memory_reserve, parameters_help
from co3sop_nodes.ros.worker import Worker
from co3sop_nodes.v2x.codec import (
    CODECS,
    FEATURE_DTYPES,
    SELECTIONS,
    FeatureCodecConfig,
    check_codec_for,
    decode_request,
)
from co3sop_nodes.v2x.neighbours import COMM_RANGE
from co3sop_nodes.v2x.request_map import request_for_neighbour
from co3sop_nodes.v2x.scan import EncodedScan, ScanCodecConfig, encode_scan
from co3sop_nodes.v2x.sender_budget import SenderBudgets
from co3sop_nodes.v2x.sender_frames import Frame, FrameAssembly
from co3sop_nodes.v2x.sender_requests import REQUEST_ANSWERS, Request, RequestBook, union_request

SENSOR_DEPTH, STATIC_DEPTH = 10, 100  # messages queued per sensor topic, and for /tf_static's mounts
SENDS = ("features", "scan")


PARAMS = (
    Param(
        "id",
        int,
        "this vehicle's CAV id, carried in its messages (--id N also puts the node in namespace /cav_<id>)",
        range=(0, 2**31 - 1),
    ),
    Param(
        "checkpoint",
        str,
        "model checkpoint: a .pt file or a shipped model by name (tiny-lidar, tiny, small); empty: tiny-lidar",
        "",
    ),
    Param(
        "modality",
        str,
        "camera or lidar, checked against the checkpoint's; empty: the checkpoint's",
        "",
        choices=("", "camera", "lidar"),
    ),
    Param(
        "range",
        str,
        "benchmark range, checked against the checkpoint's; empty: the checkpoint's",
        "",
        choices=("", *BENCHMARK_RANGES),
    ),
    Param("cameras", list, "camera names of a camera model's frame", ["camera0", "camera1", "camera2", "camera3"]),
    Param("threads", int, "torch CPU threads (several vehicles share a machine in the demo)", 1, range=(1, 256)),
    memory_reserve(64),
    Param("device", str, "where the model runs: auto (a CUDA GPU if torch sees one), cpu, cuda, cuda:N", "cpu"),
    Param(
        "precision",
        str,
        "inference precision: auto (int8 for a vehicle half with int8 weights fine-tuned for it on a CPU with "
        "AVX-512 VNNI or AMX; bfloat16 on CPUs with AMX or AVX-512 BF16 and on GPUs that have it, float16 on other "
        "GPUs, else float32), float32, bfloat16, float16, int8 (the CPU: a calibrated LiDAR vehicle half's 3D "
        "layers in int8, the rest as auto)",
        "auto",
        choices=PRECISIONS,
    ),
    Param(
        "send",
        str,
        "what goes over V2X: features (the model's, through the codec) or scan (a LiDAR model's input, the "
        "voxelised scan, co3sop_msgs/VoxelScan on voxel_scan, for each ego's copy of the model to encode; of the "
        "codec's parameters only compression, level, max_bytes and burst_bytes apply)",
        "features",
        choices=SENDS,
    ),
    Param("max_pending", int, "incomplete frames kept while waiting for their last message", 10, range=(1, 1000)),
    Param(
        "stay_current",
        bool,
        "slower than the sensors, encode the newest complete frame and skip older ones; false: encode "
        "every frame, oldest first (latency then grows)",
        True,
        True,
    ),
    Param("codec.dtype", str, "feature precision on the wire", "float16", True, choices=tuple(FEATURE_DTYPES)),
    Param(
        "codec.selection",
        str,
        "which voxels are sent: dense, topk (highest confidence), threshold, or request (confidence x "
        "the ego's request map; without one, as topk)",
        "dense",
        True,
        choices=SELECTIONS,
    ),
    Param("codec.topk", int, "voxels kept by topk", 4096, True, (1, 2**31 - 1)),
    Param("codec.threshold", float, "confidence kept by threshold", 0.5, True, (0.0, 1.0)),
    Param(
        "codec.compression",
        str,
        "payload compression: shuffle-zstd (zstd of the values byte-shuffled), zstd or none",
        FeatureCodecConfig.codec,
        True,
        choices=CODECS,
    ),
    Param("codec.level", int, "zstd level (0: the compression's own, shuffle-zstd 1, zstd 3)", 0, True, (0, 22)),
    Param(
        "request_timeout",
        float,
        "s of sensor time: an ego's request map is served by frames at most this much newer than it (the same at "
        "any play rate)",
        1.0,
        True,
        (0.0, 3600.0),
    ),
    Param("comm_range", float, "m: request maps of egos farther away are refused", COMM_RANGE, True, (0.0, 10_000.0)),
    Param("max_egos", int, "egos answered per frame with codec.selection request, nearest first", 4, True, (1, 64)),
    Param(
        "request_answer",
        str,
        "with codec.selection request: each (one message per ego, its voxels chosen by that ego's request map; "
        "every ego on the topic receives every one) or union (one message for all, its voxels chosen by their "
        "mean need)",
        "each",
        True,
        choices=REQUEST_ANSWERS,
    ),
    Param(
        "request_wait",
        float,
        "s: with codec.selection request, how long an encoded frame waits for the request map made for it by every "
        "ego that sent one lately (an ego sends it as its own frame arrives: request, then answer, in one frame); "
        "0: answered with the latest maps held, from an earlier frame",
        0.0,
        True,
        (0.0, 60.0),
    ),
    Param(
        "local_features",
        bool,
        "also publish the features losslessly on voxel_features/local, for the ego on this car when every CAV runs "
        "one (no other car's ego subscribes to it, so it never crosses the V2X link)",
        False,
    ),
    Param(
        "max_request_topics",
        int,
        "RequestMap topics subscribed at most (a flood of topics must not exhaust memory); "
        "topics whose publishers left are released first",
        32,
        range=(1, 4096),
    ),
    Param(
        "codec.max_bytes",
        int,
        "byte budget per message for topk / request (0: none; then codec.topk voxels)",
        0,
        True,
        (0, 2**31 - 1),
    ),
    Param(
        "codec.burst_bytes",
        int,
        "with codec.max_bytes: the most one message may take, max_bytes then being the average per message to each "
        "ego (what a message leaves unspent is saved for the next; 0: every message capped at max_bytes)",
        0,
        True,
        (0, 2**31 - 1),
    ),
    Param(
        "codec.rank",
        int,
        "transform coding: K coefficients per voxel on the message's own K principal directions (0: the "
        "channels as they are)",
        0,
        True,
        (0, 4096),
    ),
    Param(
        "codec.learned",
        bool,
        "send the model's learned wire code (K integers per voxel; a checkpoint trained with one, train --stage "
        "wire) instead of its features",
        False,
        True,
    ),
    Param(
        "codec.fill",
        bool,
        "with codec.selection request and codec.max_bytes: spend what the budget leaves after every voxel the egos "
        "asked for on the others, the most confident first (false: a budget the requests do not fill goes unspent)",
        False,
        True,
    ),
    Param(
        "features_reliability",
        str,
        "QoS of the published features: reliable (resends lost fragments) or best_effort (a "
        "sample with a lost fragment is dropped; only best-effort subscribers match)",
        "reliable",
        choices=tuple(RELIABILITIES),
    ),
)
CODEC_FIELDS = {
    "codec.dtype": "dtype",
    "codec.selection": "selection",
    "codec.topk": "topk",
    "codec.threshold": "threshold",
    "codec.compression": "codec",
    "codec.level": "level",
    "codec.max_bytes": "max_bytes",
    "codec.burst_bytes": "burst_bytes",
    "codec.rank": "rank",
    "codec.learned": "learned",
    "codec.fill": "fill",
}
# the codec parameters a scan takes (v2x/scan.py): ScanCodecConfig's fields
SCAN_FIELDS = tuple(f.name for f in fields(ScanCodecConfig))
REQUEST_TYPE = "co3sop_msgs/msg/RequestMap"
ANSWERING = ("request_timeout", "comm_range", "max_egos", "request_answer", "request_wait")  # how requests are served
# the ego on board gets the features as they are
LOSSLESS_CODEC = FeatureCodecConfig("float32", "dense", codec="none")


class Vehicle(ManagedNode):
    """A lifecycle node (ros/lifecycle.py): configure loads the checkpoint and creates the publishers,
    activate subscribes to the sensors; an inactive vehicle encodes nothing."""

    def __init__(self):
        super().__init__("vehicle", PARAMS)
        self.agent_id = self.params["id"]
        self.lidar_frame = topics.lidar_frame(self.agent_id)
        self.drops = DropLog(self.get_logger())
        self.published = 0
        self.inputs: SensorSubscriptions | None = None
        self.model = None
        self._requests: RequestBook | None = None  # the egos' request maps (guarded by the worker's lock)
        self._pose: np.ndarray | None = None  # world_from_lidar of the newest frame encoded
        self._request_subs: dict[str, object] = {}
        self._request_timer = None
        self._budgets: SenderBudgets | None = None
        self.skips = DropLog(self.get_logger())  # complete frames passed over for a newer one
        self._ready: list[Frame] = []  # complete frames not yet encoded, oldest first
        # woken by every complete frame; nothing is due otherwise
        self._worker = Worker(f"cav_{self.agent_id} encoder", self._take, self.get_logger(), poll_s=None)

    def configure(self) -> None:
        p = self.params
        checkpoint = p["checkpoint"]
        model, _ = load_graph_model(resolve_checkpoint(checkpoint, "parameter checkpoint"))
        self.model = model.use(model.vehicle_path(p["device"], p["precision"], what="parameter "))
        if p["precision"] == "int8" and not self.model.path.int8:
            self.get_logger().warning(f"parameter precision=int8: {self.model.int8_missing()}")
        self.cfg = cfg = self.model.cfg
        for name, have in (("modality", cfg.modality), ("range", cfg.range)):
            wanted = p[name]
            if wanted and wanted != have:
                raise Co3sopError(
                    f"parameter {name}={wanted!r}, but the checkpoint's model is {have!r}: pick a checkpoint "
                    f"trained for it"
                )
        self.kernels = compile_kernels(self.model)  # before 'active': no frame waits for a compiler
        self._code = code_id(self.model)
        self.send = p["send"]
        if self.send == "scan" and cfg.modality != "lidar":
            raise Co3sopError(f"parameter send=scan: {cfg.name} is a {cfg.modality} model (a LiDAR one sends scans)")
        self.codec = ScanCodecConfig() if self.send == "scan" else FeatureCodecConfig()
        self._apply({name: p[name] for name in (*CODEC_FIELDS, *ANSWERING)})
        p.on_change(self._apply)
        torch.set_num_threads(p["threads"])
        # a scan-only sender runs no model (its egos do). On this thread, not the encoder's: there the first frame
        # gained little and the later ones lost 15 % in the graph (BENCHMARKS.md, "Warming up on the thread that fuses")
        warmed = warm_up(self.model, ego=False) if self.send != "scan" or p["local_features"] else 0.0
        reserved = reserve_memory(p["memory_reserve_mb"] << 20)
        self.cameras = p["cameras"]
        # names relative to the node's namespace (/cav_<id> by default): `__ns` and remapping apply
        self._parts = {"pose": topics.lidar_pose()}
        self._types = {"pose": PoseStamped}
        if cfg.modality == "camera":
            for cam in self.cameras:
                self._parts[f"image:{cam}"], self._types[f"image:{cam}"] = topics.camera_image(None, cam), Image
                self._parts[f"info:{cam}"], self._types[f"info:{cam}"] = topics.camera_info(None, cam), CameraInfo
        else:
            self._parts["points"], self._types["points"] = topics.lidar_points(), PointCloud2
        self._parts = {
            k: self.resolve_topic_name(name) for k, name in self._parts.items()
        }  # full names in logs and drops
        self._pub = self.create_lifecycle_publisher(
            *((VoxelScan, topics.voxel_scan()) if self.send == "scan" else (VoxelFeatures, topics.voxel_features())),
            features_qos(p["features_reliability"]),
        )
        self._local = (
            self.create_lifecycle_publisher(VoxelFeatures, topics.local_features(), features_qos("reliable"))
            if p["local_features"]
            else None
        )
        self._diag = self.create_lifecycle_publisher(DiagnosticArray, topics.DIAGNOSTICS, DIAGNOSTICS_QOS)
        self.get_logger().info(
            f"configured: cav {self.agent_id}, {cfg.name} ({cfg.modality}, {cfg.range}), "
            + (
                f"scans {'x'.join(map(str, cfg.grid.dims))}"
                if self.send == "scan"
                else f"features {cfg.embed_dims} x {'x'.join(map(str, cfg.feature_grid.dims))}"
            )
            + f" -> {self._pub.topic_name} as {self.codec.name}, "
            f"{p['features_reliability']}{', lossless on voxel_features/local' if self._local else ''}; "
            f"inference on {self.model.path.describe()}"
            + (f" (warmed up in {warmed:.1f} s)" if warmed else "")
            + f"; compiled kernels: {', '.join(self.kernels) or 'none'}"
            + (f"; {p['memory_reserve_mb']} MB of memory reserved" if reserved else "")
        )

    def activate(self) -> None:
        self._requests = RequestBook(self.comm_range, int(self.request_timeout * 1e9), self.max_egos)
        self._tf = StaticTransforms()
        self._frames = FrameAssembly(self._parts, self.params["max_pending"], self._mounts_known, "camera mounts")
        # every input with the QoS its publisher offers (best-effort drivers, a reliable player, a latched /tf_static)
        self.inputs = SensorSubscriptions(self, self.drops)
        self.inputs.add(TFMessage, topics.TF_STATIC, self._on_static, STATIC_DEPTH)
        for key, topic in self._parts.items():
            self.inputs.add(self._types[key], topic, self._part(key), SENSOR_DEPTH)
        # every ego's request map, whatever its name or namespace (found by type, as the ego finds features)
        self._request_timer = self.create_timer(0.5, self._discover_requests)
        self._discover_requests()
        self._worker.start()

    def deactivate(self) -> None:
        self._worker.stop()
        self._ready = []
        if self.inputs is not None:
            self.inputs.close()  # half-received frames go with the assembly; mounts come again on /tf_static
            self.inputs = None
        if self._request_timer is not None:
            self.destroy_timer(self._request_timer)
        for sub in self._request_subs.values():
            self.destroy_subscription(sub)
        self._request_subs, self._request_timer, self._requests = {}, None, None

    def _discover_requests(self) -> None:
        """Sending features with codec.selection request, every RequestMap topic in the graph, up to
        max_request_topics (topics without a publisher are released); otherwise none (an ego makes its maps only
        for those who subscribe); then the links, as this vehicle sees them."""
        limit = self.params["max_request_topics"]
        new = []
        if self.send == "features" and self.codec.selection == "request":
            new = [
                name
                for name, types in self.get_topic_names_and_types()
                if REQUEST_TYPE in types and name not in self._request_subs
            ]
        else:
            for topic in list(self._request_subs):
                self._release_request(topic)
        if new and len(self._request_subs) + len(new) > limit:
            for topic in [t for t in self._request_subs if self.count_publishers(t) == 0]:
                self._release_request(topic)
        for name in new:
            if len(self._request_subs) >= limit:
                self.drops(
                    name,
                    "topics",
                    f"not subscribed: already {len(self._request_subs)} RequestMap topics (max_request_topics)",
                )
                continue
            self._request_subs[name] = subscribe_foreign(
                self, RequestMap, name, lambda msg, t=name: self._on_request(t, msg), REQUEST_QOS, self.drops
            )
        sent = {p.topic_name: p for p in (self._pub, self._local) if p is not None}
        publish_links(self, self._diag, f"vehicle cav_{self.agent_id}", self.lidar_frame, self._request_subs, sent)

    def _release_request(self, topic: str) -> None:
        """`topic`'s request maps no longer subscribed."""
        self.destroy_subscription(self._request_subs.pop(topic))
        with self._worker.lock:
            self._requests.release(topic)

    def _on_request(self, topic: str, msg: RequestMap) -> None:
        try:
            enc = request_of(msg)
            if enc.grid != self.cfg.feature_grid:
                raise Co3sopError(
                    f"grid {'x'.join(map(str, enc.grid.dims))} @ {enc.grid.voxel_size:g} m is not this "
                    f"model's feature grid"
                )
            pose = pose_of(msg.lidar_pose)
            pose.check("lidar_pose")
            need = decode_request(enc)
        except Co3sopError as exc:
            return self.drops(topic, "request", str(exc))
        if msg.agent_id == self.agent_id:  # a vehicle that is also an ego does not serve itself
            with self._worker.lock:
                self._requests.heard(topic, stamp_ns(msg.header.stamp))
                self._worker.wake()
            return
        request = Request(need, pose.matrix(), stamp_ns(msg.header.stamp))
        with self._worker.lock:
            refused = self._requests.offer(
                topic, msg.agent_id, request, self._pose, lambda t: self.count_publishers(t) > 0
            )
            self._worker.wake()  # a frame may be waiting for it
        if refused is not None:
            self.drops(topic, refused.kind, refused.reason)

    def _await_requests(self, stamp: int) -> float:
        """On the worker, with request_wait: waits (at most that long) for this frame's request map from every ego
        that sends them (sender_requests.RequestBook.awaiting); the ms waited."""
        if self.codec.selection != "request" or self.request_wait <= 0:
            return 0.0
        t0, first = time.perf_counter(), self.published == 0
        live = [t for t in list(self._request_subs) if self.count_publishers(t) > 0]
        self._worker.wait_for(lambda: not self._requests.awaiting(stamp, live, first), self.request_wait)
        return 1e3 * (time.perf_counter() - t0)

    def _recipients(self, stamp: int, world_from_lidar: np.ndarray) -> dict[int, Request]:
        """The egos whose requests this frame answers: with selection "request", the nearest with a fresh request."""
        with self._worker.lock:
            self._pose = world_from_lidar
            if self.codec.selection != "request":
                return {}
            return self._requests.serving(stamp, world_from_lidar)

    def release(self) -> None:
        self.params.on_change(None)
        for pub in ("_pub", "_local", "_diag"):
            if getattr(self, pub, None) is not None:
                self.destroy_lifecycle_publisher(getattr(self, pub))
                delattr(self, pub)
        self.model = None

    def destroy_node(self) -> None:
        self._worker.close()
        super().destroy_node()

    def _on_static(self, msg: TFMessage) -> None:
        for parent, child, parent_from_child in transforms_of(msg):
            self._tf.add(parent, child, parent_from_child)
        self._encode_ready()

    def _apply(self, values: dict) -> None:
        """The run-time parameters in `values` (at start, and on `ros2 param set`): the codec's are checked against
        this model's features (a codec that could encode no message is refused) and used from the next frame on;
        the others are read where they are used."""
        for name in ANSWERING:
            if name in values:
                setattr(self, name, values[name])
        if self._requests is not None:
            with self._worker.lock:
                self._requests.comm_range, self._requests.max_egos = self.comm_range, self.max_egos
                self._requests.timeout_ns = int(self.request_timeout * 1e9)
        codec = {CODEC_FIELDS[k]: v for k, v in values.items() if k in CODEC_FIELDS}
        if not codec:
            return
        try:
            if self.send == "scan":
                self.codec = replace(self.codec, **{k: v for k, v in codec.items() if k in SCAN_FIELDS})
                self._budgets = SenderBudgets(self.codec)
                return
            candidate = replace(self.codec, **codec)
            if candidate.learned and self.cfg.wire is None:
                raise CodecError(
                    f"codec.learned: {self.cfg.name} has no learned wire code (a checkpoint trained with one: "
                    "train --stage wire)"
                )
            channels = self.cfg.wire.rank if candidate.learned else self.cfg.embed_dims
            check_codec_for(candidate, channels, self.cfg.feature_grid)
        except CodecError as exc:
            raise Co3sopError(str(exc)) from None
        self.codec = candidate
        self._budgets = SenderBudgets(self.codec)  # bytes saved under the previous budget do not carry over

    def _encode_for(self, out, ego: int | None, request: np.ndarray | None):
        """One message's encoding for `ego` (None: every ego), within its byte budget where the codec averages one."""
        enc = encode_output(out, self.cfg.feature_grid, self._budgets.config(ego), request, self._code)
        self._budgets.spend(ego, enc.budget_bytes)
        return enc

    def _feature_messages(self, out, stamp: int, world_from_lidar: np.ndarray):
        """The frame's feature messages [(ego or None, encoding)], the requests they answer, the requests moved into
        this frame and the ms waited for them: one message per requesting ego, its voxels weighed by that ego's
        request, or one for all weighed by the union of their requests; with no request, one for all by the codec's
        own choice."""
        waited_ms = self._await_requests(stamp)
        recipients = self._recipients(stamp, world_from_lidar)
        wanted = {
            ego: request_for_neighbour(r.need, r.world_from_ego, world_from_lidar, self.cfg.feature_grid)
            for ego, r in recipients.items()
        }
        if self.request_answer == "union" and wanted:
            messages = [(None, self._encode_for(out, None, union_request(list(wanted.values()))))]
        else:
            messages = [(ego, self._encode_for(out, ego, need)) for ego, need in wanted.items()]
        return messages or [(None, self._encode_for(out, None, None))], recipients, wanted, waited_ms

    def _mounts_known(self, parts: dict) -> bool:
        """The mounts of the frame's cameras are known (topics carry no order between /tf_static and the images)."""
        return all(
            parts[f"image:{cam}"].header.frame_id in self._tf for cam in self.cameras if self.cfg.modality == "camera"
        )

    def _encode_ready(self) -> None:
        self._handle(*self._frames.ready())

    def _handle(self, frames: list[Frame], drops) -> None:
        for drop in drops:
            self.drops(self._parts.get(drop.part, topics.TF_STATIC), drop.kind, drop.reason)
        if not frames:
            return
        with self._worker.lock:
            ready = sorted([*self._ready, *frames], key=lambda f: f.stamp)
            if self.params["stay_current"]:
                ready, passed = ready[-1:], ready[:-1]
                for frame in passed:
                    self.skips(
                        self.get_namespace(),
                        "behind",
                        f"frame {frame.stamp} skipped: frame {ready[0].stamp} is complete "
                        "and this vehicle encodes slower than its sensors send",
                    )
            self._ready = ready
            self._worker.wake()

    def _take(self):
        """On the worker, under its lock: the oldest complete frame waiting (with stay_current, the only one), as a
        job."""
        if not self._ready:
            return None
        frame = self._ready.pop(0)
        return lambda: self._encode(frame)

    def _part(self, key: str):
        def callback(msg) -> None:
            self._handle(*self._frames.add(key, stamp_ns(msg.header.stamp), msg, time.time_ns()))

        return callback

    def _encode(self, frame: Frame) -> None:
        cpu0, t0 = time.process_time(), time.perf_counter()
        stamp, entry = frame.stamp, frame.parts
        try:
            pose = pose_of(entry["pose"].pose)
            pose.check(self._parts["pose"])
            world_from_lidar = pose.matrix()
            cameras, points = [], None
            if self.cfg.modality == "camera":
                for cam in self.cameras:
                    image, info = entry[f"image:{cam}"], entry[f"info:{cam}"]
                    k = intrinsics_of(info)
                    cameras.append(
                        (
                            cam,
                            rgb_of(image, self._parts[f"image:{cam}"]),
                            k,
                            self._tf.lookup(self.lidar_frame, image.header.frame_id),
                        )
                    )
            else:
                points = xyz_of(entry["points"])
            inputs = sensor_inputs(self.cfg, world_from_lidar, cameras, points)
        except Co3sopError as exc:
            return self.drops(self.get_namespace(), "input", f"frame {stamp}: {exc}")
        t1 = time.perf_counter()
        out = None  # a vehicle sending its scan runs the model only for the ego on its car
        if self.send == "features" or self._local is not None:
            with torch.inference_mode():
                out = self.model.vehicle(**to_batch(inputs, self.model.path.torch_device))
        t2 = time.perf_counter()

        def message(enc, ego: int | None):
            if isinstance(enc, EncodedScan):
                kw = dict(stamp_ns=stamp, frame_id=self.lidar_frame, agent_id=self.agent_id, pose=pose)
                return scan_msg(RCLPY, enc, **kw)
            return features_msg(
                RCLPY,
                enc,
                stamp_ns=stamp,
                frame_id=self.lidar_frame,
                agent_id=self.agent_id,
                pose=pose,
                recipient_id=ego,
            )

        fg = self.cfg.feature_grid
        try:
            # the ego on board first: it requests from the others as its frame arrives, and this frame may wait
            if self._local is not None:
                self._local.publish(message(encode_output(out, fg, LOSSLESS_CODEC), None))
            if self.send == "scan":  # the same scan for every ego
                enc = encode_scan(inputs["occupancy"][0], self.cfg.grid, self._budgets.config(None))
                self._budgets.spend(None, enc.budget_bytes)
                messages, recipients, wanted, waited_ms = [(None, enc)], {}, {}, 0.0
            else:
                messages, recipients, wanted, waited_ms = self._feature_messages(out, stamp, world_from_lidar)
        except Co3sopError as exc:  # e.g. non-finite features from extreme inputs: never sent
            return self.drops(self.get_namespace(), "encode", f"frame {stamp}: {exc}")
        msgs = [message(enc, ego) for ego, enc in messages]
        t3 = time.perf_counter()
        for msg in msgs:
            self._pub.publish(msg)
        published_wall = time.time_ns()
        self.published += 1
        values = {
            "stamp": stamp,
            "first_input_wall_ns": frame.first_wall_ns,
            "published_wall_ns": published_wall,
            "inputs_ms": f"{1e3 * (t1 - t0):.1f}",
            "encoder_ms": f"{1e3 * (t2 - t1):.1f}",
            "codec_ms": f"{1e3 * (t3 - t2) - waited_ms:.1f}",
            "request_wait_ms": f"{waited_ms:.1f}",
            "payload_bytes": sum(enc.payload_bytes for _, enc in messages),
            "recipients": ",".join(f"{ego}:{enc.budget_bytes}" for ego, enc in messages if ego is not None),
            "request_stamps": ",".join(f"{ego}:{r.stamp}" for ego, r in recipients.items()),
            "answered": ",".join(map(str, wanted)),  # the egos whose requests chose the voxels sent
            "cpu_ms": f"{1e3 * (time.process_time() - cpu0):.1f}",
            "frames_published": self.published,
            "skipped": sum(self.skips.counts.values()),
            **self.drops.values(),
        }
        self._diag.publish(
            diagnostics_msg(
                RCLPY,
                stamp,
                f"vehicle cav_{self.agent_id}",
                self.lidar_frame,
                DiagnosticStatus.OK,
                f"frame {self.published} encoded",
                values,
            )
        )


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="vehicle",
        description=__doc__.split("\n\n")[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=parameters_help((*PARAMS, AUTOSTART)),
    )
    parser.add_argument(
        "--id",
        type=int,
        help="this vehicle's CAV id: sets parameter id and, unless __ns is given, the namespace /cav_<id>",
    )
    argv = list(sys.argv if args is None else args)
    opts = parser.parse_args(remove_ros_args(argv)[1:])
    if opts.id is not None:  # one source: the parameter (as the launch files set it)
        argv += ["--ros-args", "-p", f"id:={opts.id}"]
        if not any(a.startswith("__ns:=") for a in argv):
            argv += ["-r", f"__ns:={topics.namespace(opts.id)}"]
    return spin_node(lambda: Vehicle().start(), argv, "vehicle")


if __name__ == "__main__":
    sys.exit(main())
