"""The node graph on a CAV bag, described once: recorder, the ego (or one on every CAV), one vehicle per CAV,
the player.

`demo` starts it as processes (driving the lifecycle itself) and graph.launch.py as launch_ros Nodes; both
read the nodes, their arguments and their parameters from `describe`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.data.bags import open_reader
from co3sop_nodes.ros.recorder import DEFAULT_TOPICS
from co3sop_nodes.viz.foxglove import CAMERAS

# the ego's own encoder runs on the ego: its features reach the fusion losslessly
LOSSLESS = {"codec.dtype": "float32", "codec.selection": "dense", "codec.compression": "none"}
# which CAVs run an ego: the first only, or every one (each then also a collaborator of the others)
EGOS = ("first", "all")
RECORDER_NICENESS = 10


@dataclass(frozen=True)
class NodeSpec:
    """One process of the graph. `car`: whose computer runs it ("ego", or "cav<N>" for a neighbour), which an
    emulated V2X channel puts in that car's network namespace; None: the machine's side (the simulator's player,
    the recorder), off the radio."""

    executable: str
    name: str
    car: str | None = "ego"
    namespace: str = ""
    arguments: tuple[str, ...] = ()
    parameters: dict = field(default_factory=dict)
    remappings: tuple[tuple[str, str], ...] = ()
    niceness: int = 0  # nice(1): above 0, the process takes the CPU only when the others leave it some

    @property
    def prefix(self) -> list[str]:
        """What the command line starts with, before the executable (a launch_ros Node's `prefix`)."""
        return ["nice", "-n", str(self.niceness)] if self.niceness else []

    @property
    def node(self) -> str:
        """The node's fully qualified name."""
        return f"{self.namespace}/{self.name}"

    def ros_arguments(self) -> list[str]:
        """The command line after the executable, as `ros2 run` takes it."""
        remap = ["-r", f"__ns:={self.namespace}"] if self.namespace else []
        remap += [x for a, b in self.remappings for x in ("-r", f"{a}:={b}")]
        params = [x for k, v in self.parameters.items() for x in ("-p", f"{k}:={_param_text(v)}")]
        return [*self.arguments, *(["--ros-args", *remap, *params] if remap or params else [])]


@dataclass(frozen=True)
class Graph:
    recorder: NodeSpec
    egos: tuple[NodeSpec, ...]
    vehicles: tuple[NodeSpec, ...]
    player: NodeSpec

    @property
    def nodes(self) -> tuple[NodeSpec, ...]:
        """Every process but the player, in start order."""
        return (self.recorder, *self.egos, *self.vehicles)


def _param_text(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def bag_contents(bag: Path) -> tuple[list[int], int]:
    """(CAV ids, frames) of a bag."""
    reader = open_reader(bag)
    with reader:
        poses = {
            cav[0]: c.msgcount
            for c in reader.connections
            if (cav := topics.split_cav_topic(c.topic)) is not None and c.topic == topics.lidar_pose(cav[0])
        }
    if not poses:
        raise Co3sopError(f"{bag}: no /cav_N/lidar/pose topic: not a CAV bag")
    return sorted(poses), max(poses.values())


def played_topics(cavs: list[int], sensors: str) -> list[str]:
    """What the graph listens to (so the player waits for exactly those subscribers): sensors, mounts, ground truth,
    and the ego's camera images (recorded for the Foxglove layout, whatever the model's sensors)."""
    played = [topics.TF_STATIC]
    for c in cavs:
        played.append(topics.lidar_pose(c))
        if sensors == "lidar":
            played.append(topics.lidar_points(c))
        else:
            played += [f(c, cam) for cam in CAMERAS for f in (topics.camera_image, topics.camera_info)]
        played += [topics.ground_truth(c, r) for r in topics.RANGE_SUFFIX]
    return played + [t for cam in CAMERAS if (t := topics.camera_image(cavs[0], cam)) not in played]


def answers_requests(vehicle: NodeSpec) -> bool:
    """The vehicle sends features chosen by the egos' request maps (codec.selection request), so subscribes to them."""
    params = vehicle.parameters
    return params.get("send", "features") == "features" and params.get("codec.selection", "dense") == "request"


def car_of(cav: int, cavs: list[int]) -> str:
    """The car (an emulated channel's member) of CAV `cav`: "ego" for the first, the one the machine's side
    shares memory with, "cav<N>" for the others."""
    return "ego" if cav == cavs[0] else f"cav{cav}"


def describe(
    bag: Path,
    cavs: list[int],
    sensors: str,
    recording: Path,
    rate: float,
    *,
    egos: str = "first",
    common: dict | None = None,
    ego_params: dict | None = None,
    vehicle_params: dict | None = None,
) -> Graph:
    """The graph for `cavs` of `bag`. `egos`: "first", one ego (the first CAV's, in the root namespace: /ego/...) whose
    own encoder is lossless, or "all", an ego on every CAV (in its namespace: /cav_N/ego/...), each fed its own
    car's features losslessly on board (voxel_features/local) and the others' through their V2X codec.
    `common`: parameters of every ego and vehicle (the checkpoint, device, ...); `vehicle_params`: the V2X codec.
    The recording keeps every ego's output and the first CAV's camera images (the Foxglove layout's panels)."""
    if egos not in EGOS:
        raise Co3sopError(f"egos {egos!r}: one of {', '.join(EGOS)}")
    common, first, every = dict(common or {}), cavs[0], egos == "all"
    shown = [re.escape(topics.camera_image(first, cam)) for cam in CAMERAS]
    outputs = [rf"/cav_\d+{re.escape(topics.EGO_OCCUPANCY)}"] if every else []
    recorder = NodeSpec(
        "recorder",
        "recorder",
        None,
        # lz4: the recording keeps pace with the sensors on a small machine (zstd takes twice its CPU)
        arguments=("--out", str(recording), "--compression", "lz4", "--topics", *DEFAULT_TOPICS, *outputs, *shown),
        # off the critical path: on a machine the graph keeps busy, the recorder takes what the perception nodes
        # leave and catches up from its deep queues, rather than delaying their frames
        niceness=RECORDER_NICENESS,
    )

    def ego(c: int) -> NodeSpec:
        params = {"ego_id": c, **common, **(ego_params or {})}
        if not every:
            return NodeSpec("ego", "ego", parameters=params)
        own = topics.relative(topics.voxel_features(c))  # as the ego names its own, relative to its namespace
        local = ((own, topics.local_features(c)),)
        return NodeSpec("ego", "ego", car_of(c, cavs), topics.namespace(c), parameters=params, remappings=local)

    def vehicle(c: int) -> NodeSpec:
        if every:
            params = {**(vehicle_params or {}), "local_features": True}
        else:
            params = LOSSLESS if c == first else vehicle_params or {}
        return NodeSpec(
            "vehicle", "vehicle", car_of(c, cavs), topics.namespace(c), parameters={"id": c, **common, **params}
        )

    player = NodeSpec(
        "player",
        "player",
        None,
        arguments=(
            str(bag),
            "--rate",
            str(rate),
            "--wait-subscribers",
            "30",
            "--topics",
            *played_topics(cavs, sensors),
        ),
    )
    return Graph(recorder, tuple(ego(c) for c in (cavs if every else cavs[:1])), tuple(map(vehicle, cavs)), player)
