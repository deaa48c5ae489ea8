"""The node graph over real DDS: player + vehicles + ego + recorder equal the offline path; faults are survived."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
from ament_index_python.packages import get_package_share_directory
from executables import call_failed, executable
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2

from co3sop_msgs.msg import RequestMap, VoxelFeatures, VoxelScan
from co3sop_nodes.common import topics
from co3sop_nodes.data.bags import read_frames
from co3sop_nodes.eval.bag_eval import predict_bag, vehicle_outputs
from co3sop_nodes.eval.scoring import read_recording
from co3sop_nodes.inference.checkpoint import export_model, load_model, shipped_checkpoint
from co3sop_nodes.inference.outputs import code_id, encode_output
from co3sop_nodes.messages import features_of, pose_of, request_of, scan_of, stamp_ns
from co3sop_nodes.model.co3sop import build_model, with_wire
from co3sop_nodes.model.config import WireConfig, preset
from co3sop_nodes.ros import links
from co3sop_nodes.ros.dds import OCCUPANCY_QOS
from co3sop_nodes.ros.recorder import DEFAULT_TOPICS
from co3sop_nodes.ros.supervisor import Supervisor
from co3sop_nodes.v2x.codec import FeatureCodecConfig, decode_features, decode_request
from co3sop_nodes.v2x.request_map import request_for_neighbour
from co3sop_nodes.v2x.scan import decode_scan
from co3sop_nodes.v2x.sender_budget import SenderBudgets

FRAMES = 4
# the ego fuses (and vehicles encode) every frame, waiting for every neighbour, whatever the machine keeps up with:
# the offline comparisons need them all
EVERY_FRAME = ("-p", "stay_current:=false", "-p", "max_pending:=1000")
# an ego of those waits for each neighbour's frame however late it comes (a neighbour slow to send its first frame
# on a starved CPU would be silent after neighbour_timeout, and the bag's frames fused without it)
EGO_WAITS = ("-p", "max_wait:=60.0", "-p", "neighbour_timeout:=60.0")
# a vehicle's frame waits this long for the ego's map of it: long enough for a starved CPU (the map comes as soon as
# the ego has its own frame; a wait that ran out would answer an older map)
REQUEST_WAIT_S = 30.0
CAMERA = ("-p", "checkpoint:=tiny")  # the camera model, which this file's scenario feeds (its bag's camera topics)
# offline evaluation runs float32: `auto` would take bfloat16 on a CPU with AMX or AVX-512 BF16, and the graph must
# run the same path to be compared bit for bit
FLOAT32 = ("-p", "precision:=float32")


class Graph:
    """Node processes with their output in files (a full pipe would stall a node), watched by a Supervisor:
    lifecycle states, graph events and /diagnostics decide, never the logs."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.procs: dict[str, subprocess.Popen] = {}
        self.supervisor = Supervisor("graph_test", alive=self.crashed)

    def start(self, name: str, *argv: str) -> subprocess.Popen:
        log = open(self.folder / f"{name}.log", "w")
        self.procs[name] = subprocess.Popen(list(argv), stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ))
        return self.procs[name]

    def log(self, name: str) -> str:
        return (self.folder / f"{name}.log").read_text()

    def crashed(self) -> str | None:
        """Why the graph cannot go on: a node that failed (a test's own kill -9 excepted), with its log."""
        for name, proc in self.procs.items():
            if proc.poll() not in (None, 0, -signal.SIGKILL):
                return f"{name} failed ({proc.returncode}):\n{self.log(name)}"
        return None

    def wait_active(self, *nodes: str) -> None:
        for node in nodes:
            self.supervisor.wait_state(node, "active", timeout=180)

    def wait_linked(self, cavs: list[int], topic=topics.voxel_features, ego: str = "ego") -> None:
        """Every CAV's `topic` linked at both ends (`wait_links`)."""
        self.wait_links({c: topic(c) for c in cavs}, ego)

    def wait_links(self, links: dict[int, str], ego: str = "ego") -> None:
        """Each vehicle's topic in `links` linked at both ends by the nodes' own account (their links status, as the
        demo waits before playing): the ego matched to the vehicle's publisher (or it fuses a first frame without it)
        and the vehicle's publisher to the ego's reader (a frame it sends before that is lost)."""
        sup = self.supervisor
        for c, t in links.items():
            sup.wait(
                f"{t} linked from vehicle cav_{c} to {ego}",
                lambda t=t, c=c: sup.linked(ego, receives=[t]) and sup.linked(f"vehicle cav_{c}", sends=[t]),
                60,
            )

    def wait_fused(self, n: int, where=lambda report: True, timeout: float = 180, ego: str = "ego") -> list[dict]:
        """The /diagnostics reports of the ego whose status is `ego` (its node's name) once `n` satisfy `where`."""
        return self.supervisor.wait_reports(ego, n, timeout, where)

    def stop(self, name: str, sig=signal.SIGINT, timeout: float = 30) -> int:
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(sig)
        return proc.wait(timeout)

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in self.procs.values():
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
        self.supervisor.close()

    def print_logs(self, lines: int = 40) -> None:
        """The last `lines` of every node's log (with the test's report: what a failure in CI leaves to go by)."""
        for name in self.procs:
            tail = self.log(name).splitlines()[-lines:]
            print(f"--- {name} (exit {self.procs[name].returncode}), its last {len(tail)} lines:", *tail, sep="\n")


@pytest.fixture
def graph(tmp_path, request):
    g = Graph(tmp_path)
    yield g
    g.close()
    if call_failed(request):
        g.print_logs()


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> tuple[Path, list[int]]:
    """A small generated scenario bag (the demo's town and traffic, smaller images) and its CAV ids."""
    root = tmp_path_factory.mktemp("scenario")
    done = subprocess.run(
        [
            executable("generate"),
            "--out",
            str(root / "data"),
            "--bags",
            str(root / "bags"),
            "--splits",
            "test=1",
            "--frames",
            str(FRAMES),
            "--cavs",
            "3",
            "--seed",
            "7",
            "--image-size",
            "160x120",
            "--lidar-steps",
            "256",
            "--workers",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    bag = next((root / "bags" / "test").iterdir())
    cavs = sorted(int(p.name) for p in next((root / "data" / "test").iterdir()).iterdir() if p.is_dir())
    return bag, cavs


def run_graph(
    graph: Graph,
    bag: Path,
    cavs: list[int],
    vehicle_params: list[str],
    ego_params: list[str] = (),
    recorded: tuple[str, ...] = (),
    before_play=lambda: None,
) -> Path:
    """Recorder (its default topics, or `recorded`), ego (the first CAV), one vehicle per CAV; `before_play()`; the
    bag played once; everything stopped; the MCAP path."""
    mcap = graph.folder / "run.mcap"
    graph.start("recorder", executable("recorder"), "--out", str(mcap), *(("--topics", *recorded) if recorded else ()))
    graph.start(
        "ego",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={cavs[0]}",
        *EGO_WAITS,
        *EVERY_FRAME,
        *CAMERA,
        *FLOAT32,
        *ego_params,
    )
    for c in cavs:
        graph.start(
            f"vehicle{c}",
            executable("vehicle"),
            "--id",
            str(c),
            "--ros-args",
            *EVERY_FRAME,
            *CAMERA,
            *FLOAT32,
            *[x for p in vehicle_params for x in ("-p", p)],
        )
    graph.wait_active("/ego", *map(topics.vehicle_node, cavs))
    graph.wait_linked(cavs)
    # every topic of the nodes' that the recorder records, taken before the first frame: the recorder subscribes as
    # it discovers a publisher, and a topic it takes late has lost its first messages (volatile)
    patterns = [re.compile(f"^{t}$") for t in (recorded or DEFAULT_TOPICS)]
    for topic in (topics.EGO_OCCUPANCY, topics.DIAGNOSTICS, *map(topics.voxel_features, cavs)):
        if any(p.match(topic) for p in patterns):
            graph.supervisor.wait_subscribed("/recorder", topic)
    played = ["/tf_static"] + [
        f"/cav_{c}/{s}"
        for c in cavs
        for s in [
            "lidar/pose",
            "ground_truth/occupancy_50m",
            *(f"camera{i}/{k}" for i in range(4) for k in ("image_raw", "camera_info")),
        ]
    ]
    before_play()
    play_and_stop(graph, bag, cavs, played)
    return mcap


def play_and_stop(graph: Graph, bag: Path, cavs: list[int], played: list[str]) -> None:
    """The `played` topics of the bag played once, every frame fused, then the vehicles, the ego and the recorder
    stopped."""
    player = graph.start(
        "player", executable("player"), str(bag), "--rate", "0.5", "--wait-subscribers", "30", "--topics", *played
    )
    assert player.wait(120) == 0, graph.log("player")
    graph.wait_fused(FRAMES)
    for c in cavs:
        graph.stop(f"vehicle{c}")
    graph.stop("ego")
    assert graph.stop("recorder") == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (CI has none)")
@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_graph_on_a_cuda_gpu_predicts_as_offline_on_the_cpu(graph, scenario, precision):
    """Every node's model on the GPU: the same frames fused, labels as the CPU's float32 reference within the
    tolerance of a different device (cuDNN's own kernels, TF32 convolutions) or reduced precision: at least 99 %
    of voxels equal."""
    bag, cavs = scenario
    on_gpu = ["device:=cuda", f"precision:={precision}"]
    mcap = run_graph(graph, bag, cavs, on_gpu, ego_params=[x for p in on_gpu for x in ("-p", p)])
    rec = read_recording(mcap)
    assert len(rec.predictions) == FRAMES
    assert all(int(d["neighbours_used"]) >= 1 for d in rec.diagnostics["ego"]), rec.diagnostics
    assert f"inference on cuda, {precision}" in graph.log("ego"), graph.log("ego")

    torch.set_num_threads(1)
    model, _ = load_model(shipped_checkpoint("tiny.pt"))
    offline = predict_bag(model, bag, cavs[0], FeatureCodecConfig("float32", "dense", codec="none"))
    equal = sum(int((labels == offline[stamp].labels).sum()) for (_, stamp), labels in rec.predictions.items())
    total = sum(labels.size for labels in rec.predictions.values())
    print(f"{precision} on {torch.cuda.get_device_name()}: labels equal to the CPU's float32 on {equal / total:.4%}")
    assert equal / total >= 0.99


@pytest.mark.parametrize(
    "codec",
    [  # a sparse quantised message's path is also the learned code's test's
        FeatureCodecConfig("float32", "dense", codec="none"),
        pytest.param(FeatureCodecConfig("int8", "topk", topk=1024), marks=pytest.mark.heavy),
    ],
    ids=lambda c: c.name,
)
def test_graph_predictions_equal_offline_evaluation(graph, scenario, codec):
    bag, cavs = scenario
    params = [
        f"codec.dtype:={codec.dtype}",
        f"codec.selection:={codec.selection}",
        f"codec.topk:={codec.topk}",
        f"codec.compression:={codec.codec}",
    ]
    mcap = run_graph(graph, bag, cavs, params)
    rec = read_recording(mcap)
    published = len(graph.supervisor.reports("ego"))
    assert len(rec.predictions) == published == FRAMES  # the recording holds every prediction the ego published
    assert all(int(d["neighbours_used"]) >= 1 for d in rec.diagnostics["ego"]), (
        rec.diagnostics
    )  # collaboration really ran

    torch.set_num_threads(1)  # as the nodes run: same kernels, same float results
    model, _ = load_model(shipped_checkpoint("tiny.pt"))
    offline = predict_bag(model, bag, cavs[0], codec)
    assert sorted(offline) == sorted(s for _, s in rec.predictions)
    for (agent, stamp), labels in rec.predictions.items():
        assert agent == cavs[0]
        assert np.array_equal(labels, offline[stamp].labels), (
            f"frame {stamp}: {(labels != offline[stamp].labels).mean():.2%} of voxels differ"
        )
    assert rec.truths.keys() == rec.predictions.keys()


def test_a_learned_code_crosses_dds_as_its_integers_and_decodes_as_offline(graph, scenario, tmp_path):
    """Vehicles send a model's learned wire code (codec.learned: 4 integers per voxel, int4, no constants, basis or
    confidence; named by the code) for their 1024 most confident voxels; the ego decodes it with the same code's
    decoder and fuses: every prediction equals offline evaluation through the same codec, bit for bit."""
    bag, cavs = scenario
    torch.manual_seed(3)
    wired = with_wire(load_model(shipped_checkpoint("tiny.pt"))[0], WireConfig(4, 7))
    checkpoint = tmp_path / "wired.pt"
    export_model(checkpoint, wired, {})
    model, _ = load_model(checkpoint)
    codec = FeatureCodecConfig("int4", "topk", topk=1024, learned=True)
    params = [f"checkpoint:={checkpoint}", "codec.dtype:=int4", "codec.selection:=topk", "codec.topk:=1024"]
    params.append("codec.learned:=true")
    features = "/cav_.*/voxel_features"
    mcap = run_graph(
        graph,
        bag,
        cavs,
        params,
        ego_params=["-p", f"checkpoint:={checkpoint}"],
        recorded=(features, topics.EGO_OCCUPANCY, topics.DIAGNOSTICS, "/cav_.*/ground_truth/occupancy_50m"),
    )
    sent = [features_of(m) for _, m in recorded_messages(mcap, features, VoxelFeatures)]
    assert len(sent) == FRAMES * len(cavs)
    assert all(
        (e.learned_code, e.channels, e.dtype, e.num_voxels, e.has_confidence, e.quant_scale, e.basis)
        == (code_id(model), 4, "int4", 1024, False, (), ())
        for e in sent
    )
    rec = read_recording(mcap)
    assert all(int(d["neighbours_used"]) >= 1 for d in rec.diagnostics["ego"]), rec.diagnostics["ego"]  # fused
    torch.set_num_threads(1)  # as the nodes run: same kernels, same float results
    offline = predict_bag(model, bag, cavs[0], codec)
    assert sorted(offline) == sorted(s for _, s in rec.predictions)
    for (_, stamp), labels in rec.predictions.items():
        assert np.array_equal(labels, offline[stamp].labels), f"frame {stamp}"


def test_lidar_scans_cross_dds_and_the_ego_encodes_them_as_their_senders(graph, scenario):
    """Neighbours send their voxelised LiDAR scans (send:=scan) in place of features; the ego runs its copy of the
    LiDAR model on each and fuses: every prediction equals offline evaluation with the neighbours' features sent
    losslessly, bit for bit."""
    bag, cavs = scenario
    ego, lidar = cavs[0], ("-p", "checkpoint:=tiny-lidar", *FLOAT32)
    scans, mcap = "/cav_.*/voxel_scan", graph.folder / "run.mcap"
    recorded = (scans, re.escape(topics.EGO_OCCUPANCY), re.escape(topics.DIAGNOSTICS), r"/cav_\d+/ground_truth/\w+")
    graph.start("recorder", executable("recorder"), "--out", str(mcap), "--topics", *recorded)
    graph.start("ego", executable("ego"), "--ros-args", "-p", f"ego_id:={ego}", *EGO_WAITS, *EVERY_FRAME, *lidar)
    for c in cavs:
        send = ("codec.dtype:=float32", "codec.compression:=none") if c == ego else ("send:=scan",)
        args = [x for p in send for x in ("-p", p)]
        graph.start(f"vehicle{c}", executable("vehicle"), "--id", str(c), "--ros-args", *EVERY_FRAME, *lidar, *args)
    graph.wait_active("/ego", *map(topics.vehicle_node, cavs))
    graph.wait_linked([ego])
    graph.wait_linked(cavs[1:], topics.voxel_scan)
    assert "scans 256x256x24 -> /cav_" in graph.log(f"vehicle{cavs[1]}")
    graph.supervisor.wait_subscribed("/recorder", topics.EGO_OCCUPANCY)
    played = ["/tf_static"] + [
        f"/cav_{c}/{s}" for c in cavs for s in ("lidar/pose", "lidar/points", "ground_truth/occupancy_50m")
    ]
    play_and_stop(graph, bag, cavs, played)

    sent = recorded_messages(mcap, scans, VoxelScan)
    assert sorted(topic for topic, _ in sent) == sorted(topics.voxel_scan(c) for c in cavs[1:] for _ in range(FRAMES))
    assert all(0 < decode_scan(scan_of(m)).sum() == m.num_voxels for _, m in sent)
    rec = read_recording(mcap)
    assert all(int(d["neighbours_used"]) >= 1 for d in rec.diagnostics["ego"]), rec.diagnostics["ego"]  # fused
    torch.set_num_threads(1)  # as the nodes run: same kernels, same float results
    model, _ = load_model(shipped_checkpoint("tiny-lidar.pt"))
    offline = predict_bag(model, bag, ego, FeatureCodecConfig("float32", "dense", codec="none"))
    assert sorted(offline) == sorted(s for _, s in rec.predictions)
    for (_, stamp), labels in rec.predictions.items():
        assert np.array_equal(labels, offline[stamp].labels), f"frame {stamp}"


def recorded_messages(mcap: Path, topic_pattern: str, msg_type) -> list[tuple[str, object]]:
    """(topic, message) of every message on topics matching the pattern, in log order."""
    with open(mcap, "rb") as f:
        return [
            (channel.topic, deserialize_message(message.data, msg_type))
            for _, channel, message in make_reader(f).iter_messages()
            if re.fullmatch(topic_pattern, channel.topic)
        ]


@pytest.mark.parametrize(
    "dtype, rank, budget, burst",
    [  # the last takes every path the others do (transform coding, a budget) and the int4 and burst ones besides
        pytest.param("int8", 0, 20000, 0, marks=pytest.mark.heavy),
        pytest.param("int8", 8, 20000, 0, marks=pytest.mark.heavy),
        ("int4", 8, 2000, 8000),
    ],
    ids=["channels", "rank8", "rank8-int4-burst"],
)
def test_request_maps_round_trip_within_budget_and_bit_exact(graph, scenario, dtype, rank, budget, burst):
    """A request map reaches the vehicles (a stand-in's from before the first frame, then the ego's own of each
    frame, sent as the ego's own frame arrives, which each vehicle's frame waits for: request_wait, ended when the map
    comes); each vehicle answers it with the voxels it weighs highest under its byte budget, addressed to the ego;
    what arrives is what the same computation gives offline, byte for byte, and only where the ego asked. With
    codec.rank the message carries 8 coefficients per voxel (int4: two per byte) and its own basis; with
    codec.burst_bytes the budget is an average per message (a token bucket, full at the start), what a message leaves
    unspent going to the next."""
    bag, cavs = scenario
    codec = FeatureCodecConfig(dtype, "request", max_bytes=budget, burst_bytes=burst, rank=rank)
    params = [
        f"codec.dtype:={dtype}",
        "codec.selection:=request",
        f"codec.max_bytes:={budget}",
        f"codec.burst_bytes:={burst}",
        f"codec.rank:={rank}",
        "request_timeout:=60.0",
        f"request_wait:={REQUEST_WAIT_S}",
        "comm_range:=1000.0",
    ]  # every neighbour answers, near or far
    torch.set_num_threads(1)
    model, _ = load_model(shipped_checkpoint("tiny.pt"))
    fg = model.cfg.feature_grid
    outputs = vehicle_outputs(model, bag)
    first = min(outputs)
    world_from_ego = outputs[first][cavs[0]][1]
    stand_in = first - 1_000_000  # just before the first frame: a request ages in sensor time

    def ask() -> None:  # the stand-in ego's request, known to every vehicle before it encodes a frame
        graph.start(
            "requester",
            sys.executable,
            str(Path(__file__).parent / "peers" / "requester.py"),
            str(cavs[0]),
            str(stand_in),
            json.dumps(world_from_ego.tolist()),
            model.cfg.range,
        )
        for c in cavs[1:]:
            graph.supervisor.wait_subscribed(topics.vehicle_node(c), topics.EGO_REQUEST)
        time.sleep(1.0)

    mcap = run_graph(
        graph,
        bag,
        cavs,
        params,
        recorded=("/cav_.*/voxel_features", topics.EGO_REQUEST, topics.DIAGNOSTICS, topics.EGO_OCCUPANCY),
        before_play=ask,
    )
    requests = {
        stamp_ns(m.header.stamp): m for _, m in recorded_messages(mcap, re.escape(topics.EGO_REQUEST), RequestMap)
    }
    assert stand_in in requests and len(requests) >= FRAMES  # the stand-in's, and the ego's after each of its frames
    assert all(m.agent_id == cavs[0] for m in requests.values())
    features = recorded_messages(mcap, r"/cav_\d+/voxel_features", VoxelFeatures)
    addressed = [(t, m) for t, m in features if m.addressed]
    assert addressed and all(m.recipient_id == cavs[0] for _, m in addressed)  # the only ego
    used, waited = {}, {}  # (vehicle, frame stamp) -> the request stamp it answered, and the ms it waited for one
    for name, statuses in read_recording(mcap).diagnostics.items():
        if name.startswith("vehicle ") and not name.endswith(links.SUFFIX):
            for status in statuses:
                key = int(name.split("_")[1]), int(status["stamp"])
                waited[key] = float(status["request_wait_ms"])
                for item in filter(None, status["request_stamps"].split(",")):
                    used[key] = int(item.split(":")[1])
    # every frame answers the ego's map of that very frame, which came (the first: the stand-in's, or the ego's if
    # the ego's own encoder was quicker than the vehicle's)
    assert all(asked == stamp or (stamp, asked) == (first, stand_in) for (_, stamp), asked in used.items()), used
    assert all(waited[key] < REQUEST_WAIT_S * 1e3 for key in used), waited
    assert len(addressed) >= FRAMES * (len(cavs) - 1)  # every neighbour frame (the ego's own encoder is not asked)
    carried, budgets, spent = 0, {}, {}
    for _, msg in sorted(
        addressed, key=lambda tm: (tm[1].agent_id, stamp_ns(tm[1].header.stamp))
    ):  # each sender's in order
        enc = features_of(msg)
        assert enc.budget_bytes <= (burst or budget)
        sender = budgets.setdefault(msg.agent_id, SenderBudgets(codec))
        spent[msg.agent_id] = spent.get(msg.agent_id, []) + [enc.budget_bytes]
        assert (
            sum(spent[msg.agent_id]) <= (burst or budget) + (len(spent[msg.agent_id]) - 1) * budget
        )  # a token bucket's bound
        request = requests[used[msg.agent_id, stamp_ns(msg.header.stamp)]]
        need = decode_request(request_of(request))
        out, world_from_vehicle = outputs[stamp_ns(msg.header.stamp)][msg.agent_id]
        wanted = request_for_neighbour(need, pose_of(request.lidar_pose).matrix(), world_from_vehicle, fg)
        expected = encode_output(out, fg, sender.config(cavs[0]), wanted)
        sender.spend(cavs[0], expected.budget_bytes)
        assert (
            enc.dtype,
            enc.voxel_mask,
            enc.values,
            enc.confidence,
            enc.quant_scale,
            enc.basis_rank,
            enc.basis,
            enc.basis_mean,
        ) == (
            dtype,
            expected.voxel_mask,
            expected.values,
            expected.confidence,
            expected.quant_scale,
            rank,
            expected.basis,
            expected.basis_mean,
        ), f"cav {msg.agent_id}"
        sent = decode_features(enc).confidence.reshape(-1) > 0
        assert (
            wanted.reshape(-1)[sent] > 0
        ).all()  # only voxels the ego asked for (none where it asked nothing in view)
        carried += int(sent.sum())
    assert carried > 0
    if burst:  # the bucket starts full: a first answer takes more than the average
        assert max(max(sizes) for sizes in spent.values()) > budget


def test_two_egos_each_get_answers_to_their_own_requests(graph, scenario):
    """Two egos at once (one in the root namespace, one under /b), each with its own lossless encoder; the third
    vehicle answers each ego's request map with a message addressed to it; each ego fuses the answer to its own
    request and ignores the other's."""
    bag, cavs = scenario
    a, b, c = cavs
    checkpoint = Path(get_package_share_directory("co3sop_nodes"), "checkpoints", "tiny-lidar.pt")
    lidar = ["-p", f"checkpoint:={checkpoint}"]
    dense = ["-p", "codec.dtype:=float32", "-p", "codec.compression:=none"]
    graph.start("ego_a", executable("ego"), "--ros-args", "-p", f"ego_id:={a}", *EGO_WAITS, *EVERY_FRAME, *lidar)
    graph.start(
        "ego_b",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={b}",
        *EGO_WAITS,
        *EVERY_FRAME,
        *lidar,
        "-r",
        "__ns:=/b",
        "-r",
        f"cav_{b}/voxel_features:={topics.voxel_features(b)}",
    )
    for v in (a, b):
        graph.start(f"vehicle{v}", executable("vehicle"), "--id", str(v), "--ros-args", *lidar, *dense, *EVERY_FRAME)
    graph.start(
        f"vehicle{c}",
        executable("vehicle"),
        "--id",
        str(c),
        "--ros-args",
        *lidar,
        *EVERY_FRAME,
        "-p",
        "codec.dtype:=int8",
        "-p",
        "codec.selection:=request",
        "-p",
        "codec.max_bytes:=20000",
        "-p",
        "request_timeout:=60.0",
    )
    graph.wait_active("/ego", "/b/ego", *map(topics.vehicle_node, cavs))
    sup = graph.supervisor
    for ego, others in (("/ego", (b, c)), ("/b/ego", (a, c))):
        for v in others:
            sup.wait_subscribed(ego, topics.voxel_features(v))
    poses = {stamp: agents for stamp, agents in read_frames(bag)}
    first = min(poses)
    for ego, topic in ((a, topics.EGO_REQUEST), (b, "/b" + topics.EGO_REQUEST)):  # stand-ins, before the first frame
        graph.start(
            f"requester{ego}",
            sys.executable,
            str(Path(__file__).parent / "peers" / "requester.py"),
            str(ego),
            str(first),  # stamped as the first frame: a request ages in sensor time
            json.dumps(poses[first][ego]["pose"].tolist()),
            "51.2m",
            topic,
        )
        # the requester's publisher in the graph (it starts slowly on 2 cores): the vehicle gets its latched request
        # as soon as they match, within the seconds below even on a machine loaded by the rest of the suite, so even
        # the first frame is answered
        sup.wait_subscribed(topics.vehicle_node(c), topic)
        sup.wait_published("/requester", topic)
    time.sleep(3.0)
    played = ["/tf_static", *(t for v in cavs for t in (topics.lidar_pose(v), topics.lidar_points(v)))]
    player = graph.start(
        "player", executable("player"), str(bag), "--rate", "0.5", "--wait-subscribers", "30", "--topics", *played
    )
    assert player.wait(120) == 0, graph.log("player")
    reports = sup.wait_reports("ego", FRAMES, timeout=180) + sup.wait_reports("b/ego", FRAMES, timeout=180)
    by_ego = {v: [r for r in reports if r["received_wall_ns"].startswith(f"{v}:")] for v in (a, b)}
    answered = [r["recipients"] for r in sup.reports(f"vehicle cav_{c}")]
    assert all({int(x.split(":")[0]) for x in rec.split(",")} == {a, b} for rec in answered), answered
    for ego in (a, b):
        assert len(by_ego[ego]) == FRAMES
        # the answer to its request arrived in time (fused, or matched but beyond comm_range)
        assert all(str(c) in (r["neighbours"] + "," + r["neighbours_not_chosen"]).split(",") for r in by_ego[ego]), (
            by_ego[ego]
        )
        # the other ego's answers, ignored: every frame's before its last frame's (the vehicle sends them in order)
        assert int(by_ego[ego][-1]["messages_for_other_egos"]) >= FRAMES - 1
    assert all(int(x.split(":")[1]) <= 20000 for rec in answered for x in rec.split(","))


def test_ego_keeps_publishing_when_a_vehicle_dies(graph, scenario):
    bag, cavs = scenario
    ego, neighbour = cavs[0], cavs[-1]
    mcap = graph.folder / "run.mcap"
    graph.start("recorder", executable("recorder"), "--out", str(mcap), "--topics", "/diagnostics", "/ego/occupancy")
    # frames come 5 s apart (rate 0.02): a neighbour is silent only after more than that; max_age 0: a dead neighbour's
    # last frame is not fused in place of the ones it no longer sends
    graph.start(
        "ego",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={ego}",
        "-p",
        "max_wait:=1.0",
        "-p",
        "neighbour_timeout:=8.0",
        "-p",
        "max_age:=0.0",
        *CAMERA,
    )
    for c in (ego, neighbour):
        graph.start(f"vehicle{c}", executable("vehicle"), "--id", str(c), "--ros-args", *CAMERA)
    graph.wait_active("/ego", topics.vehicle_node(ego), topics.vehicle_node(neighbour))
    graph.wait_linked([ego, neighbour])
    for topic in ("/diagnostics", "/ego/occupancy"):  # recorded from the first frame on, as the demo makes sure
        graph.supervisor.wait_subscribed("/recorder", topic)
    played = ["/tf_static"] + [
        f"/cav_{c}/{s}"
        for c in (ego, neighbour)
        for s in ["lidar/pose", *(f"camera{i}/{k}" for i in range(4) for k in ("image_raw", "camera_info"))]
    ]
    graph.start(
        "player", executable("player"), str(bag), "--rate", "0.02", "--wait-subscribers", "30", "--topics", *played
    )
    graph.wait_fused(1, lambda r: r["neighbours_used"] == "1")
    graph.procs[f"vehicle{neighbour}"].kill()  # no goodbye: as a crash
    graph.wait_fused(1, lambda r: r["neighbours_used"] == "0" and r["neighbours_missing"] == str(neighbour))
    assert graph.procs["ego"].poll() is None
    graph.stop("player")
    graph.stop("ego")
    assert graph.stop("recorder") == 0
    diags = read_recording(mcap).diagnostics["ego"]
    assert diags[0]["neighbours_used"] == "1"  # fused while alive, from the first frame on
    assert diags[-1]["neighbours_used"] == "0" and diags[-1]["neighbours_missing"] == str(neighbour)


def test_ego_fuses_a_lidar_vehicle_beside_a_camera_one(graph, scenario, tmp_path):
    """The cheap modality: a LiDAR encoder (LMSCNet, same feature grid) as a neighbour of the camera ego."""
    bag, cavs = scenario
    ego, neighbour = cavs[0], cavs[-1]
    lidar = tmp_path / "lidar.pt"
    torch.manual_seed(0)
    export_model(lidar, build_model(preset("tiny-lmscnet")), {"made_by": "test: random weights"})
    graph.start("ego", executable("ego"), "--ros-args", "-p", f"ego_id:={ego}", *EGO_WAITS, *EVERY_FRAME, *CAMERA)
    graph.start("camera", executable("vehicle"), "--id", str(ego), "--ros-args", *EVERY_FRAME, *CAMERA)
    graph.start(
        "lidar",
        executable("vehicle"),
        "--id",
        str(neighbour),
        "--ros-args",
        *EVERY_FRAME,
        "-p",
        f"checkpoint:={lidar}",
        "-p",
        "modality:=lidar",
    )
    graph.wait_active("/ego", topics.vehicle_node(ego), topics.vehicle_node(neighbour))
    graph.wait_linked([ego, neighbour])
    assert "tiny-lmscnet (lidar" in graph.log("lidar")
    played = [
        "/tf_static",
        f"/cav_{neighbour}/lidar/pose",
        f"/cav_{neighbour}/lidar/points",
        f"/cav_{ego}/lidar/pose",
        *(f"/cav_{ego}/camera{i}/{k}" for i in range(4) for k in ("image_raw", "camera_info")),
    ]
    graph.start(
        "player", executable("player"), str(bag), "--rate", "0.5", "--wait-subscribers", "30", "--topics", *played
    )
    graph.wait_fused(2, lambda r: r["neighbours_used"] == "1")


def test_vehicle_and_ego_follow_the_node_lifecycle(graph, scenario):
    """With autostart:=false nothing is loaded, published or subscribed until a manager configures and activates;
    deactivate stops the work, cleanup releases the publishers (and configure loads again), shutdown finalises;
    a configure that fails says why and leaves the node unconfigured."""
    bag, cavs = scenario
    ego, neighbour = cavs[0], cavs[-1]
    sup, manual = graph.supervisor, ["-p", "autostart:=false"]
    graph.start(
        "ego",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={ego}",
        *EGO_WAITS,
        *EVERY_FRAME,
        *manual,
        *CAMERA,
    )
    for c in (ego, neighbour):
        graph.start(f"vehicle{c}", executable("vehicle"), "--id", str(c), "--ros-args", *manual, *EVERY_FRAME, *CAMERA)
    graph.start(
        "broken",
        executable("vehicle"),
        "--id",
        "99",
        "--ros-args",
        *manual,
        "-p",
        f"checkpoint:={graph.folder / 'missing.pt'}",
    )
    broken = topics.vehicle_node(99)
    nodes = ["/ego", topics.vehicle_node(ego), topics.vehicle_node(neighbour)]
    for node in [*nodes, broken]:
        sup.wait_state(node, "unconfigured")
    assert sup.node.count_publishers(topics.EGO_OCCUPANCY) == sup.node.count_publishers(topics.voxel_features(ego)) == 0

    assert not sup.change(broken, "configure")
    assert sup.state(broken) == "unconfigured" and "missing.pt" in graph.log("broken")
    for node in nodes:
        assert sup.change(node, "configure") and sup.state(node) == "inactive"
    # the default reserves, written at configure
    assert "256 MB of memory reserved" in graph.log("ego")
    assert "64 MB of memory reserved" in graph.log(f"vehicle{neighbour}")
    sup.wait(
        "the publishers made by configure",
        lambda: (
            sup.node.count_publishers(topics.EGO_OCCUPANCY) == 1
            and sup.node.count_publishers(topics.voxel_features(neighbour)) == 1
        ),
        30,
    )
    assert not sup.subscribes("/ego", topics.voxel_features(ego))  # an inactive ego listens to nothing

    for node in nodes:
        assert sup.change(node, "activate") and sup.state(node) == "active"
    graph.wait_linked([ego, neighbour])
    played = ["/tf_static"] + [
        f"/cav_{c}/{s}"
        for c in (ego, neighbour)
        for s in ["lidar/pose", *(f"camera{i}/{k}" for i in range(4) for k in ("image_raw", "camera_info"))]
    ]
    player = graph.start(
        "player", executable("player"), str(bag), "--rate", "0.5", "--wait-subscribers", "30", "--topics", *played
    )
    assert player.wait(120) == 0, graph.log("player")
    graph.wait_fused(FRAMES, lambda r: r["neighbours_used"] == "1")

    vehicle = topics.vehicle_node(ego)
    assert sup.change(vehicle, "deactivate") and sup.state(vehicle) == "inactive"
    sup.wait(
        "the inactive vehicle to drop its sensor subscriptions",
        lambda: not sup.subscribes(vehicle, topics.lidar_pose(ego)),
        30,
    )
    assert sup.change("/ego", "deactivate")
    sup.wait(
        "the inactive ego to unsubscribe", lambda: not sup.subscribes("/ego", topics.voxel_features(neighbour)), 30
    )
    assert sup.change("/ego", "cleanup") and sup.state("/ego") == "unconfigured"
    sup.wait(
        "cleanup to release the ego's publishers",
        lambda: (
            sup.node.count_publishers(topics.EGO_OCCUPANCY) == 0 and sup.node.count_publishers(topics.EGO_REQUEST) == 0
        ),
        30,
    )
    assert sup.change("/ego", "configure") and sup.change("/ego", "activate")  # loads again after a cleanup
    sup.wait_subscribed("/ego", topics.voxel_features(neighbour))
    for node in [*nodes, broken]:
        assert sup.change(node, "shutdown") and sup.state(node) == "finalized"
    assert len(graph.supervisor.reports("ego")) == FRAMES  # nothing fused while inactive or after


def foxglove_decode(*paths: Path) -> dict:
    """Per file and topic: what Foxglove's own readers (npm: @mcap/core, @foxglove/rosmsg2-serialization) decode."""
    script = Path(__file__).resolve().parents[1] / "foxglove" / "decode.mjs"
    done = subprocess.run(["node", str(script), *map(str, paths)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def mcap_counts(path: Path) -> dict[str, int]:
    with open(path, "rb") as f:
        return dict(Counter(channel.topic for _, channel, _ in make_reader(f).iter_messages()))


def test_recordings_and_bags_decode_with_foxglove_readers_and_draw_in_3d(graph, scenario):
    """Every message of a graph recording and of a generated bag decodes with Foxglove's own readers, and the
    recording holds the ego's prediction and its ground truth as coloured points in the ego's LiDAR frame."""
    bag, cavs = scenario
    live: dict[int, bytes] = {}  # a live viewer's clouds, by stamp: the ego makes them while one subscribes

    def viewer() -> None:
        def seen(raw: bytes) -> None:
            msg = deserialize_message(raw, PointCloud2)
            live[stamp_ns(msg.header.stamp)] = bytes(msg.data)

        sub = graph.supervisor.node.create_subscription(PointCloud2, topics.EGO_POINTS, seen, OCCUPANCY_QOS, raw=True)
        graph.supervisor.wait("the viewer matched with the ego", lambda: sub.get_publisher_count() == 1, 60)
        time.sleep(1.0)  # and the ego with the viewer (discovery completes on both sides, not at once)

    mcap = run_graph(graph, bag, cavs, [], before_play=viewer)
    files = [mcap, *bag.glob("*.mcap")]
    decoded = foxglove_decode(*files)
    for path in files:
        topics_ = decoded[str(path)]
        assert "error" not in topics_, topics_
        failed = {t: e for t, e in topics_.items() if e["failed"] or e["error"]}
        assert not failed, failed
        assert {t: e["decoded"] for t, e in topics_.items()} == mcap_counts(
            path
        )  # every message, as the mcap library counts
    rec = decoded[str(mcap)]
    # the recorder draws the prediction's points itself: the same points the ego sends a live viewer
    drawn = {
        stamp_ns(m.header.stamp): bytes(m.data)
        for _, m in recorded_messages(mcap, re.escape(topics.EGO_POINTS), PointCloud2)
    }
    assert len(live) == len(drawn) == FRAMES and live == drawn
    for topic in (topics.EGO_POINTS, topics.EGO_TRUTH_POINTS):
        assert rec[topic]["decoded"] == FRAMES and rec[topic]["schema"] == "sensor_msgs/msg/PointCloud2"
        sample = rec[topic]["sample"]
        assert sample["frame_id"] == topics.lidar_frame(cavs[0]) and sample["fields"] == ["x", "y", "z", "rgb", "label"]
        assert sample["width"] > 1000, sample


def test_namespaces_and_remapping_apply_to_every_node_topic(graph, scenario):
    """Nodes name their topics relative to their namespace: the ego under /fleet, its own encoder under /fleet/car_a
    reading the bag's topics through remapping, a neighbour publishing on a name of its own; the ego finds that
    neighbour in the graph by message type, and fuses it."""
    bag, cavs = scenario
    ego, neighbour = cavs[0], cavs[-1]
    lidar = ["-p", f"checkpoint:={Path(get_package_share_directory('co3sop_nodes'), 'checkpoints', 'tiny-lidar.pt')}"]
    graph.start(
        "ego",
        executable("ego"),
        "--ros-args",
        "-p",
        f"ego_id:={ego}",
        *EGO_WAITS,
        *EVERY_FRAME,
        *lidar,
        "-r",
        "__ns:=/fleet",
        "-r",
        f"cav_{ego}/voxel_features:=/fleet/car_a/voxel_features",
    )
    graph.start(
        "own",
        executable("vehicle"),
        "--id",
        str(ego),
        "--ros-args",
        *lidar,
        *EVERY_FRAME,
        "-r",
        "__ns:=/fleet/car_a",
        "-r",
        f"lidar/pose:={topics.lidar_pose(ego)}",
        "-r",
        f"lidar/points:={topics.lidar_points(ego)}",
    )
    graph.start(
        "neighbour",
        executable("vehicle"),
        "--id",
        str(neighbour),
        "--ros-args",
        *lidar,
        *EVERY_FRAME,
        "-r",
        "voxel_features:=/v2x/any_name",
    )
    graph.wait_active("/fleet/ego", "/fleet/car_a/vehicle", topics.vehicle_node(neighbour))
    graph.wait_links({ego: "/fleet/car_a/voxel_features", neighbour: "/v2x/any_name"}, ego="fleet/ego")
    sup = graph.supervisor
    assert (
        sup.node.count_publishers("/fleet/ego/occupancy") == 1 and sup.node.count_publishers(topics.EGO_OCCUPANCY) == 0
    )
    assert (
        sup.node.count_publishers(topics.voxel_features(ego))
        == sup.node.count_publishers(topics.voxel_features(neighbour))
        == 0
    )
    played = ["/tf_static", *(t for c in (ego, neighbour) for t in (topics.lidar_pose(c), topics.lidar_points(c)))]
    player = graph.start(
        "player", executable("player"), str(bag), "--rate", "0.5", "--wait-subscribers", "30", "--topics", *played
    )
    assert player.wait(120) == 0, graph.log("player")
    reports = graph.wait_fused(FRAMES, lambda r: r["neighbours"] == str(neighbour), ego="fleet/ego")
    assert all(r["neighbours_missing"] == "" for r in reports), reports
    assert "/fleet/car_a/voxel_features" in graph.log("own") and "neighbour discovered: /v2x/any_name" in graph.log(
        "ego"
    )
