"""`ego`: fuses its own and its neighbours' voxel features and publishes the semantic occupancy.

    ros2 run co3sop_nodes ego --ros-args -p ego_id:=1 [--params-file ego.yaml]

Subscribes to its own encoder's cav_<ego_id>/voxel_features (a name relative
to its namespace, so remapping works) and to every other topic of type
co3sop_msgs/VoxelFeatures or co3sop_msgs/VoxelScan (a neighbour's LiDAR scan,
which this ego's model encodes) as it appears in the graph, whatever its name
(up to max_topics); a neighbour's vehicle id is the one its first message carries
(the vehicle's own /cav_N/voxel_features, or a topic whose claimant left,
takes it over). Each message is
checked (valid CDR, agent id, pose, grid, payload, finite values, size limit,
age) and decoded on
arrival; a bad one is dropped and counted by reason, with a warning naming the
topic and the reason once per burst. Each of its own frames waits (at most
max_wait s) for every live neighbour's frame within `tolerance` s of its stamp
(the rules: v2x/ego_pairing.py); behind its input, it fuses the newest frame that
is ready and skips the older ones (counted as `skipped`), so its latency stays
bounded at any play rate; frames are fused on a thread of their own
(worker.py) while the executor keeps receiving. The ego keeps the nearest max_collaborators within
comm_range m, optionally perturbs their poses (Co3SOP's pose noise),
runs the model's ego half and publishes ego/occupancy
(co3sop_msgs/SemanticOccupancy), ego/occupancy/points (PointCloud2: x, y, z,
rgb, label; while someone subscribes) and its diagnostics on /diagnostics (neighbours used and missing,
their age, bytes received, time per stage, drops by reason). A lifecycle node
(ros/lifecycle.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import PointCloud2

from co3sop_msgs.msg import RequestMap, SemanticOccupancy, VoxelFeatures, VoxelScan
from co3sop_nodes.common import topics
from co3sop_nodes.common.allocation import reserve_memory
from co3sop_nodes.common.errors import Co3sopError, NonFiniteError, PayloadTooLargeError
from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.inference.checkpoint import load_graph_model, resolve_checkpoint
from co3sop_nodes.inference.outputs import decoded_output, scan_output
from co3sop_nodes.inference.pace import warm_up
from co3sop_nodes.inference.predict import compile_kernels, predict_frame
from co3sop_nodes.messages import (
    diagnostics_msg,
    features_of,
    occupancy_msg,
    point_cloud_msg,
    pose_of,
    request_msg,
    scan_of,
    stamp_ns,
)
from co3sop_nodes.model.co3sop import VehicleOutput
from co3sop_nodes.model.path import PRECISIONS
from co3sop_nodes.ros.dds import (
    DIAGNOSTICS_QOS,
    OCCUPANCY_QOS,
    RELIABILITIES,
    REQUEST_QOS,
    DropLog,
    features_qos,
    spin_node,
    subscribe_foreign,
)
from co3sop_nodes.ros.lifecycle import AUTOSTART, ManagedNode
from co3sop_nodes.ros.links import publish_links
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.ros.params import Param, memory_reserve, parameters_help
from co3sop_nodes.ros.worker import Worker
from co3sop_nodes.v2x.codec import REQUEST_LEVELS, decode_features, encode_labels, encode_request
from co3sop_nodes.v2x.ego_pairing import Pairing, PairingConfig
from co3sop_nodes.v2x.neighbours import COMM_RANGE
from co3sop_nodes.v2x.request_map import request_of
from co3sop_nodes.viz.cloud import occupancy_cloud, occupancy_cloud_reference

PARAMS = (
    Param(
        "ego_id",
        int,
        "the CAV this ego runs on: its own features come on cav_<ego_id>/voxel_features (relative: remap it "
        "where its encoder publishes elsewhere)",
        range=(0, 2**31 - 1),
    ),
    Param(
        "checkpoint",
        str,
        "model checkpoint, the vehicles' model: a .pt file or a shipped model by name (tiny-lidar, tiny, "
        "small); empty: tiny-lidar",
        "",
    ),
    Param(
        "tolerance",
        float,
        "s: a neighbour's frame pairs with the ego's within this (and is waited for, up to max_wait)",
        0.05,
        True,
        (0.0, 10.0),
    ),
    Param(
        "max_age",
        float,
        "s: a neighbour whose frame of the ego's stamp never came (it skipped it, or it is late) is fused "
        "with its nearest frame this close to the stamp, placed by its own pose at its own stamp",
        0.5,
        True,
        (0.0, 10.0),
    ),
    Param("comm_range", float, "m: neighbours farther away are not used", COMM_RANGE, True, (0.0, 10_000.0)),
    Param("max_collaborators", int, "the nearest neighbours used, at most the model's maximum", 6, True, (0, 64)),
    Param("max_wait", float, "s: how long a frame waits for live neighbours", 2.0, True, (0.0, 600.0)),
    Param(
        "neighbour_timeout",
        float,
        "s: a neighbour silent this long (while the ego's frames flow) is not waited for",
        5.0,
        True,
        (0.0, 3600.0),
    ),
    Param(
        "pose_noise_mu",
        float,
        "m: Co3SOP's pose noise on neighbours, dx, dy ~ N(mu, sigma)",
        0.0,
        True,
        (-100.0, 100.0),
    ),
    Param(
        "pose_noise_sigma",
        float,
        "m: Co3SOP's pose noise on neighbours, dx, dy ~ N(mu, sigma)",
        0.0,
        True,
        (0.0, 100.0),
    ),
    Param("seed", int, "seed of the pose noise", 0),
    Param(
        "max_stamp_ahead",
        float,
        "s: a message stamped further ahead of this node's clock (the bag's /clock under "
        "use_sim_time) is refused, so one glitching or hostile stamp cannot make later frames look stale",
        1.0,
        True,
        (0.0, 3600.0),
    ),
    Param(
        "max_payload_mb",
        float,
        "declared uncompressed payloads above this are refused before decompressing",
        64.0,
        True,
        (0.001, 65536.0),
    ),
    Param(
        "publish_points",
        bool,
        "also publish /ego/occupancy/points (PointCloud2) for RViz2 and Foxglove, while they subscribe",
        True,
        True,
    ),
    Param(
        "request_maps",
        bool,
        "publish /ego/request_map as each own frame arrives, while someone subscribes (vehicles with codec.selection "
        "request do)",
        True,
        True,
    ),
    Param(
        "request_levels",
        int,
        "levels of the request map's need (2: whether it is above a half, about 0.2 KB a map; 256: about 17 KB)",
        256,
        True,
        REQUEST_LEVELS,
    ),
    Param("threads", int, "torch CPU threads", 1, range=(1, 256)),
    memory_reserve(256),
    Param("device", str, "where the model runs: auto (a CUDA GPU if torch sees one), cpu, cuda, cuda:N", "cpu"),
    Param(
        "precision",
        str,
        "inference precision: auto (int8 for a head fine-tuned for it on a CPU with AVX-512 VNNI or AMX; bfloat16 "
        "on CPUs with AMX or AVX-512 BF16 and on GPUs that have it, "
        "float16 on other GPUs, else float32), float32, bfloat16, float16, int8 (the CPU: a calibrated LiDAR "
        "model's head up to 1/2 in int8, and the vehicle halves it runs on neighbours' scans; the rest as auto)",
        "auto",
        choices=PRECISIONS,
    ),
    Param(
        "queue_depth",
        int,
        "messages per neighbour topic held by DDS until taken (the ego takes them as they come)",
        10,
        range=(1, 1000),
    ),
    Param(
        "max_pending",
        int,
        "own frames waiting for neighbours at once; one more ends the oldest's wait (behind its input, "
        "the ego fuses the newest ready frame and skips older ones)",
        PairingConfig.max_pending,
        True,
        (1, 1000),
    ),
    Param(
        "stay_current",
        bool,
        "behind its input, fuse the newest ready own frame and skip older ones; false: fuse every own "
        "frame, oldest first (to record every frame of a bag played faster than the ego fuses; latency then grows)",
        True,
        True,
    ),
    Param(
        "features_reliability",
        str,
        "QoS of the features subscriptions: reliable, or best_effort (matches both kinds of "
        "vehicle; a reliable subscription does not match a best-effort vehicle)",
        "reliable",
        choices=tuple(RELIABILITIES),
    ),
    Param(
        "max_topics",
        int,
        "VoxelFeatures topics subscribed at most (a flood of topics must not exhaust memory); topics "
        "whose publishers left are released first",
        32,
        range=(1, 4096),
    ),
    Param(
        "discovery_period", float, "s between looks for new VoxelFeatures topics in the graph", 0.5, range=(0.01, 60.0)
    ),
    Param(
        "reference_paths",
        bool,
        "the PyTorch reference paths instead of the compiled kernels (same outputs, slower)",
        False,
    ),
)
RUNTIME = [p.name for p in PARAMS if p.runtime]
# what a neighbour sends: its features, or its LiDAR scan for this ego's model to encode
NEIGHBOUR_TYPES = {"co3sop_msgs/msg/VoxelFeatures": VoxelFeatures, "co3sop_msgs/msg/VoxelScan": VoxelScan}


@dataclass
class Received:
    agent: int
    stamp: int
    out: VehicleOutput
    world_from_lidar: np.ndarray  # (4, 4)
    wire_bytes: int
    received_wall_ns: int
    decode_ms: float


class Ego(ManagedNode):
    """A lifecycle node (ros/lifecycle.py): configure loads the checkpoint and creates the publishers,
    activate subscribes to the vehicles' features and starts fusing; an inactive ego fuses nothing."""

    def __init__(self):
        super().__init__("ego", PARAMS)
        self.ego_id = self.params["ego_id"]
        # its own encoder's features: cav_<ego_id>/voxel_features, relative (remap it to where that encoder publishes)
        self.own_topic = self.resolve_topic_name(topics.relative(topics.voxel_features(self.ego_id)))
        # its status on /diagnostics: the node's name ("ego"; "cav_3/ego" for an ego in /cav_3, one per CAV)
        self.status_name = self.get_fully_qualified_name().lstrip("/")
        self.drops = DropLog(self.get_logger())
        self.published = 0
        self._subs: dict[str, object] = {}
        self._agents: dict[str, int] = {}  # a neighbour's topic -> its vehicle, from its first accepted message
        self.for_other_egos = 0  # features addressed to another ego (its request map), ignored
        self._timers: list = []
        self.model = None
        self.skips = DropLog(self.get_logger())  # own frames passed over for a newer one, logged once per burst
        self._skipped_seen = 0
        # fusing on its own thread; `lock` guards the pairing, which the executor's callbacks fill
        self._worker = Worker("ego fusion", self._take, self.get_logger())

    def configure(self) -> None:
        p = self.params
        model, _ = load_graph_model(resolve_checkpoint(p["checkpoint"], "parameter checkpoint"))
        # the reference paths (PyTorch warp and sampling, dense head, cloud by index arrays): the same outputs, slower;
        # for bench_graph's same-run ratios
        self.reference_paths = p["reference_paths"]
        path = model.ego_path(p["device"], p["precision"], compiled=not self.reference_paths, what="parameter ")
        self.model = model.use(path)
        if path.int8 and not self.model.path.int8 and self.model.cfg.modality == "lidar":  # it may encode scans
            self.get_logger().warning(f"parameter precision=int8: {self.model.int8_missing()}")
        self.cfg = self.model.cfg
        self.kernels = compile_kernels(self.model, points=True)  # before 'active': no frame waits for a compiler
        self.pairing: Pairing[str, Received] = Pairing(self.own_topic)
        self._apply({name: p[name] for name in RUNTIME})
        p.on_change(self._apply)
        self.rng = np.random.default_rng(p["seed"])
        torch.set_num_threads(p["threads"])
        warmed = self._worker.call(lambda: warm_up(self.model, ego=True))  # on the thread that fuses
        reserved = reserve_memory(p["memory_reserve_mb"] << 20)
        # messages wait in DDS only until the executor takes them (fusing runs on its own thread)
        self._qos = features_qos(p["features_reliability"], p["queue_depth"])
        # names relative to the node's namespace: `__ns` and remapping apply
        self._occupancy = self.create_lifecycle_publisher(
            SemanticOccupancy, topics.relative(topics.EGO_OCCUPANCY), OCCUPANCY_QOS
        )
        self._points = self.create_lifecycle_publisher(PointCloud2, topics.relative(topics.EGO_POINTS), OCCUPANCY_QOS)
        self._request = self.create_lifecycle_publisher(RequestMap, topics.relative(topics.EGO_REQUEST), REQUEST_QOS)
        self._diag = self.create_lifecycle_publisher(DiagnosticArray, topics.DIAGNOSTICS, DIAGNOSTICS_QOS)
        self.get_logger().info(
            f"configured: ego cav {self.ego_id}, {self.cfg.name} ({self.cfg.range}), up to "
            f"{self.max_collaborators} collaborators within {self.comm_range:g} m; "
            f"inference on {self.model.path.describe()}"
            + (f" (warmed up in {warmed:.1f} s)" if warmed else "")
            + f"; compiled kernels: {', '.join(self.kernels) or 'none'}"
            + (f"; {p['memory_reserve_mb']} MB of memory reserved" if reserved else "")
        )

    def activate(self) -> None:
        with self._worker.lock:
            self.pairing = Pairing(self.own_topic, self.pairing.cfg)  # nothing waits from before a deactivation
        self._skipped_seen = 0
        self._subscribe(self.own_topic)
        self._timers = [self.create_timer(self.params["discovery_period"], self._discover)]
        self._discover()
        self._worker.start()

    def deactivate(self) -> None:
        self._worker.stop()
        for timer in self._timers:
            self.destroy_timer(timer)
        for sub in self._subs.values():
            self.destroy_subscription(sub)
        self._timers, self._subs, self._agents = [], {}, {}

    def release(self) -> None:
        self.params.on_change(None)
        for pub in ("_occupancy", "_points", "_request", "_diag"):
            if hasattr(self, pub):
                self.destroy_lifecycle_publisher(getattr(self, pub))
                delattr(self, pub)
        self.model = None

    def destroy_node(self) -> None:
        self._worker.close()
        super().destroy_node()

    def _apply(self, values: dict) -> None:
        """Takes the run-time parameters in `values` (at start, and on `ros2 param set`), after checking them."""
        if values.get("max_collaborators", 0) > self.cfg.max_collaborators:
            raise Co3sopError(
                f"max_collaborators {values['max_collaborators']} is above the model's {self.cfg.max_collaborators}"
            )
        cfg = self.pairing.cfg
        self.pairing.cfg = replace(
            cfg,
            tolerance_ns=int(values.get("tolerance", cfg.tolerance_ns / 1e9) * 1e9),
            max_wait_s=values.get("max_wait", cfg.max_wait_s),
            neighbour_timeout_ns=int(values.get("neighbour_timeout", cfg.neighbour_timeout_ns / 1e9) * 1e9),
            max_pending=values.get("max_pending", cfg.max_pending),
            stay_current=values.get("stay_current", cfg.stay_current),
            max_age_ns=int(values.get("max_age", cfg.max_age_ns / 1e9) * 1e9),
        )
        for name in (
            "comm_range",
            "max_collaborators",
            "pose_noise_mu",
            "pose_noise_sigma",
            "publish_points",
            "request_maps",
            "request_levels",
            "max_stamp_ahead",
        ):
            if name in values:
                setattr(self, name, values[name])
        if "max_payload_mb" in values:
            self.max_raw_bytes = int(values["max_payload_mb"] * 2**20)

    # --- receiving ---------------------------------------------------------------------------------

    def _subscribe(self, topic: str, msg_type: type = VoxelFeatures) -> None:
        if topic != self.own_topic:
            with self._worker.lock:
                self.pairing.discovered(topic, time.time_ns())
        sub = subscribe_foreign(
            self,
            msg_type,
            topic,
            lambda msg, raw, t=topic: self._on_features(t, msg, raw),
            self._qos,
            self.drops,
            raw=True,
        )
        with self._worker.lock:  # the worker reads the subscriptions (for the topics still silent)
            self._subs[topic] = sub

    def _discover(self, links: bool = True) -> None:
        """Every VoxelFeatures or VoxelScan topic in the graph is a neighbour's, whatever its name or namespace, up
        to max_topics (to make room, topics without a publisher left are released); then, with `links` or where a
        topic was subscribed, the links as this ego sees them."""
        new = {
            name: NEIGHBOUR_TYPES[kind]
            for name, types in self.get_topic_names_and_types()
            for kind in types[:1]  # a topic of two types is one DDS cannot carry: its first, as `ros2 topic` shows
            if kind in NEIGHBOUR_TYPES and name not in self._subs and not self._another_cars_own(name)
        }
        if new and len(self._subs) + len(new) > self.params["max_topics"]:
            self._release_silent()
        for name in new:
            if len(self._subs) >= self.params["max_topics"]:
                self.drops(name, "topics", f"not subscribed: already {len(self._subs)} neighbour topics (max_topics)")
                continue
            self._subscribe(name, new[name])
            self.get_logger().info(f"neighbour discovered: {name}")
            links = True
        if not links:
            return
        with self._worker.lock:
            subs = dict(self._subs)
        publish_links(self, self._diag, self.status_name, topics.lidar_frame(self.ego_id), subs)

    def _another_cars_own(self, topic: str) -> bool:
        """Features not meant for this ego, never subscribed: another car's on board (voxel_features/local) and,
        where this ego's own come on board, its own car's V2X transmission (/cav_<ego_id>/voxel_features or
        voxel_scan)."""
        return topic != self.own_topic and (
            topics.is_local_features(topic)
            or topic in (topics.voxel_features(self.ego_id), topics.voxel_scan(self.ego_id))
        )

    def _release_silent(self) -> None:
        """Unsubscribes from neighbour topics that have no publisher left, forgetting their vehicle and frames."""
        for topic in [t for t in self._subs if t != self.own_topic and not self._has_publisher(t)]:
            self.destroy_subscription(self._subs[topic])
            with self._worker.lock:
                del self._subs[topic]
                self._agents.pop(topic, None)
                self.pairing.forget(topic)

    def _agent_of(self, topic: str, msg: VoxelFeatures | VoxelScan) -> int:
        """The vehicle behind `topic`: the ego's own on its own topic; a neighbour's id is fixed by its first message."""
        agent = msg.agent_id
        if topic == self.own_topic:
            if agent != self.ego_id:
                raise Co3sopError(f"agent_id {agent} on the ego's own features, expected {self.ego_id}")
            return agent
        known = self._agents.get(topic)
        if known is not None and agent != known:
            raise Co3sopError(f"agent_id {agent} does not match the vehicle {known} this topic carried so far")
        if known is None:
            if agent == self.ego_id:
                raise Co3sopError(f"agent_id {agent} is the ego's, on another topic than {self.own_topic}")
            other = next((t for t, a in self._agents.items() if a == agent), None)
            if other is not None:
                # the id stays with its first topic while that has a publisher, unless this topic is the vehicle's own
                # by the namespace convention: a squatter neither locks the real vehicle out nor outlives its publisher
                if self.count_publishers(other) > 0 and topic != topics.voxel_features(agent):
                    raise Co3sopError(f"agent_id {agent} is already published on {other}")
                with self._worker.lock:
                    del self._agents[other]
                    self.pairing.forget(other)
                self.get_logger().warning(f"vehicle {agent} now on {topic}, no longer on {other}")
            self._agents[topic] = agent
        return agent

    def _on_features(self, topic: str, msg: VoxelFeatures | VoxelScan, raw: bytes) -> None:
        wall = time.time_ns()
        stamp = stamp_ns(msg.header.stamp)
        scan = isinstance(msg, VoxelScan)
        # features selected for another ego's request: not ours to fuse
        if not scan and msg.addressed and msg.recipient_id != self.ego_id:
            self.for_other_egos += 1
            return
        try:
            agent = self._agent_of(topic, msg)
            pose = pose_of(msg.lidar_pose)
            pose.check("lidar_pose")
        except Co3sopError as exc:
            return self.drops(topic, "header", str(exc))
        now = self.get_clock().now().nanoseconds  # 0 under use_sim_time before the first /clock: no bound yet
        if now and stamp > now + self.max_stamp_ahead * 1e9:
            return self.drops(
                topic,
                "future",
                f"stamp {stamp} is {(stamp - now) / 1e9:.3f} s ahead of this node's clock, more than "
                f"max_stamp_ahead {self.max_stamp_ahead:g} s",
            )
        with self._worker.lock:
            stale, repeated = self.pairing.stale(stamp), topic == self.own_topic and self.pairing.repeated(stamp)
        if repeated:
            return self.drops(
                topic, "repeated", f"own frame {stamp} was fused already or waits to be (a duplicate or a replay)"
            )
        if stale:
            age_ms, reach_ms = (self.pairing.last_fused - stamp) / 1e6, self.pairing.cfg.reach_ns / 1e6
            return self.drops(
                topic,
                "stale",
                f"stamp {stamp} is {age_ms:.0f} ms older than the last fused frame, "
                f"more than max_age / tolerance ({reach_ms:.0f} ms)",
            )
        t0 = time.perf_counter()
        try:
            if scan and topic == self.own_topic:
                raise Co3sopError(f"a VoxelScan on the ego's own features topic {self.own_topic}")
            if scan:  # encoded by this ego's model as the sender's would
                out = scan_output(scan_of(msg), self.model, self.max_raw_bytes)
            else:
                out = self._decode_features(msg)
        except PayloadTooLargeError as exc:
            return self.drops(topic, "size", str(exc))
        except NonFiniteError as exc:
            return self.drops(topic, "non_finite", str(exc))
        except Co3sopError as exc:  # GridError, CodecError: a bad grid or a corrupt / truncated payload
            return self.drops(topic, "payload", str(exc))
        if topic == self.own_topic:
            # a neighbour that appeared since the last discovery tick is waited for with this frame; the links are
            # the tick's to report (each report costs more than the look)
            self._discover(links=False)
            if self.request_maps and self._request.get_subscription_count():  # only vehicles that use them subscribe
                self._publish_request(stamp, out.confidence, pose)
        record = Received(agent, stamp, out, pose.matrix(), len(raw), wall, 1e3 * (time.perf_counter() - t0))
        with self._worker.lock:
            self.pairing.add(topic, stamp, record, wall, time.monotonic())
            self._worker.wake()

    def _decode_features(self, msg: VoxelFeatures) -> VehicleOutput:
        """A VoxelFeatures message -> the sender's output as fusion takes it; raises Co3sopError on a bad one."""
        enc = features_of(msg)
        # a learned code carries its K integers per voxel, which this model's decoder of the code expands
        channels = self.cfg.wire.rank if enc.learned_code and self.cfg.wire else self.cfg.embed_dims
        if enc.grid != self.cfg.feature_grid or enc.channels != channels:
            raise Co3sopError(
                f"grid {'x'.join(map(str, enc.grid.dims))} @ {enc.grid.voxel_size:g} m x {enc.channels} channels "
                f"does not match the model's {'x'.join(map(str, self.cfg.feature_grid.dims))} @ "
                f"{self.cfg.feature_grid.voxel_size:g} m x {channels}"
            )
        return decoded_output(decode_features(enc, max_raw_bytes=self.max_raw_bytes), self.model)

    def _publish_request(self, stamp: int, confidence: torch.Tensor, pose: Pose) -> None:
        """Where this own frame is unsure (v2x/request_map.py), as it arrives: the vehicles answer it with this
        frame (those that wait for it: request_wait) or their next."""
        need = encode_request(request_of(confidence), self.cfg.feature_grid, levels=self.request_levels)
        frame = topics.lidar_frame(self.ego_id)
        self._request.publish(request_msg(RCLPY, need, stamp_ns=stamp, frame_id=frame, agent_id=self.ego_id, pose=pose))

    # --- fusing ------------------------------------------------------------------------------------

    def _has_publisher(self, topic: str) -> bool:
        return self.count_publishers(topic) > 0

    def _take(self):
        """On the worker, under its lock: the newest own frame ready to fuse with its neighbours' frames, as a
        job; older ones are skipped."""
        stamp = self.pairing.next_due(time.time_ns(), time.monotonic(), self._has_publisher)
        if stamp is None:
            return None
        if self.pairing.skipped > self._skipped_seen:
            n, self._skipped_seen = self.pairing.skipped - self._skipped_seen, self.pairing.skipped
            for _ in range(n):
                self.skips(
                    self.own_topic,
                    "behind",
                    "frames skipped: a newer own frame was ready (the ego fuses slower than its input comes)",
                )
        ego = self.pairing.match(self.own_topic, stamp)
        if ego is None:  # evicted by newer own frames while waiting
            return None
        heard = self.pairing.heard()
        matched = {
            r.agent: r
            for t in heard
            if (r := self.pairing.match(t, stamp) or self.pairing.nearest(t, stamp)) is not None
        }
        missing = sorted(a for t in heard if (a := self._agents.get(t)) is not None and a not in matched)
        # discovered, yet not one frame received (a link that cannot carry its features, say): by topic, no id is known
        silent = sorted(t for t in self._subs if t != self.own_topic and t not in self._agents)
        self.pairing.fused(stamp)  # from now on, frames older than this one are stale
        return lambda: self._fuse(stamp, ego, matched, missing, silent)

    def _fuse(
        self, stamp: int, ego: Received, matched: dict[int, Received], missing: list[int], silent: list[str]
    ) -> None:
        cpu0, t0 = time.process_time(), time.perf_counter()
        candidates = {a: (r.out, r.world_from_lidar) for a, r in matched.items()}
        pred = predict_frame(
            self.model,
            ego.out,
            ego.world_from_lidar,
            candidates,
            self.comm_range,
            self.max_collaborators,
            self.pose_noise_mu,
            self.pose_noise_sigma,
            self.rng,
        )
        chosen, others = pred.collaborators, [matched[a] for a in pred.collaborators]
        t2 = time.perf_counter()
        frame = topics.lidar_frame(self.ego_id)
        enc = encode_labels(pred.labels, self.cfg.grid, self.cfg.num_classes, confidence=pred.confidence)
        self._occupancy.publish(occupancy_msg(RCLPY, enc, stamp_ns=stamp, frame_id=frame, agent_id=self.ego_id))
        published_wall = time.time_ns()
        # a frame's megabytes of points only for a live viewer: the recorder draws its own from /ego/occupancy
        if self.publish_points and self._points.get_subscription_count():
            cloud = (occupancy_cloud_reference if self.reference_paths else occupancy_cloud)(pred.labels, self.cfg.grid)
            self._points.publish(point_cloud_msg(RCLPY, cloud, stamp_ns=stamp, frame_id=frame))
        t3 = time.perf_counter()
        self.published += 1
        out_of_range = [a for a in matched if a not in chosen]
        used = [ego, *others]
        values = {
            "stamp": stamp,
            "neighbours_used": len(others),
            "neighbours": ",".join(map(str, chosen)),
            "neighbours_missing": ",".join(map(str, missing)),
            "neighbours_silent": ",".join(silent),
            "neighbours_not_chosen": ",".join(map(str, out_of_range)),
            "neighbour_age_ms": ",".join(f"{(stamp - r.stamp) / 1e6:.0f}" for r in others),
            "received_wall_ns": ",".join(f"{a}:{r.received_wall_ns}" for a, r in zip([self.ego_id, *chosen], used)),
            "bytes_received": sum(r.wire_bytes for r in used),
            "bytes_per_agent": ",".join(f"{a}:{r.wire_bytes}" for a, r in zip([self.ego_id, *chosen], used)),
            "decode_ms": f"{sum(r.decode_ms for r in used):.1f}",
            "fuse_ms": f"{1e3 * pred.fuse_s:.1f}",
            "head_ms": f"{1e3 * pred.head_s:.1f}",
            "publish_ms": f"{1e3 * (t3 - t2):.1f}",
            "total_ms": f"{1e3 * (t3 - t0):.1f}",
            "published_wall_ns": published_wall,
            "cpu_ms": f"{1e3 * (time.process_time() - cpu0):.1f}",
            "frames_published": self.published,
            "messages_for_other_egos": self.for_other_egos,
            "skipped": sum(self.skips.counts.values()),
            **self.drops.values(),
        }
        level = DiagnosticStatus.WARN if missing or silent else DiagnosticStatus.OK
        text = (
            f"{len(others)} neighbours used"
            + (f"; no frame from cav {', '.join(map(str, missing))}" if missing else "")
            + (f"; nothing received yet on {', '.join(silent)}" if silent else "")
        )
        self._diag.publish(diagnostics_msg(RCLPY, stamp, self.status_name, frame, level, text, values))
        self.get_logger().info(f"frame {stamp}: published #{self.published}, {text}, {1e3 * (t3 - t0):.0f} ms")


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    parser = argparse.ArgumentParser(
        prog="ego",
        description=__doc__.split("\n\n")[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=parameters_help((*PARAMS, AUTOSTART)),
    )
    parser.parse_args(remove_ros_args(argv)[1:])  # --help, or a usage error for anything but ROS arguments
    return spin_node(lambda: Ego().start(), argv, "ego")


if __name__ == "__main__":
    sys.exit(main())
