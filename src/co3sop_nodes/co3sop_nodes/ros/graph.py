"""The node graph on a CAV bag, described once: recorder, ego, one vehicle per CAV, the player.

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


@dataclass(frozen=True)
class NodeSpec:
    """One process of the graph. `car`: whose computer runs it ("ego", or "cav<N>" for a neighbour), which an
    emulated V2X channel puts in that car's network namespace."""

    executable: str
    name: str
    car: str = "ego"
    namespace: str = ""
    arguments: tuple[str, ...] = ()
    parameters: dict = field(default_factory=dict)

    def ros_arguments(self) -> list[str]:
        """The command line after the executable, as `ros2 run` takes it."""
        remap = ["-r", f"__ns:={self.namespace}"] if self.namespace else []
        params = [x for k, v in self.parameters.items() for x in ("-p", f"{k}:={_param_text(v)}")]
        return [*self.arguments, *(["--ros-args", *remap, *params] if remap or params else [])]


@dataclass(frozen=True)
class Graph:
    recorder: NodeSpec
    ego: NodeSpec
    vehicles: tuple[NodeSpec, ...]
    player: NodeSpec

    @property
    def nodes(self) -> tuple[NodeSpec, ...]:
        """Every process but the player, in start order."""
        return (self.recorder, self.ego, *self.vehicles)


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


def describe(
    bag: Path,
    cavs: list[int],
    sensors: str,
    recording: Path,
    rate: float,
    *,
    common: dict | None = None,
    ego_params: dict | None = None,
    vehicle_params: dict | None = None,
) -> Graph:
    """The graph for `cavs` of `bag` (the first is the ego). `common`: parameters of the ego and every vehicle (the
    checkpoint, device, ...); `vehicle_params`: the neighbours' (their V2X codec), the ego's own encoder is
    lossless; the recording also keeps the ego's camera images (the Foxglove layout's panels)."""
    common, ego = dict(common or {}), cavs[0]
    shown = [re.escape(topics.camera_image(ego, cam)) for cam in CAMERAS]
    recorder = NodeSpec(
        "recorder", "recorder", arguments=("--out", str(recording), "--topics", *DEFAULT_TOPICS, *shown)
    )
    ego_node = NodeSpec("ego", "ego", parameters={"ego_id": ego, **common, **(ego_params or {})})
    vehicles = tuple(
        NodeSpec(
            "vehicle",
            "vehicle",
            "ego" if c == ego else f"cav{c}",
            topics.namespace(c),
            parameters={"id": c, **common, **(LOSSLESS if c == ego else vehicle_params or {})},
        )
        for c in cavs
    )
    player = NodeSpec(
        "player",
        "player",
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
    return Graph(recorder, ego_node, vehicles, player)
