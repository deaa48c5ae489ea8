"""The whole graph on a CAV bag, as `demo` runs it: recorder, ego, one vehicle per CAV, the player.

    ros2 launch co3sop_nodes graph.launch.py bag:=bags/demo/test/SCENARIO [model:=tiny-lidar] [vehicles:=3]
        [egos:=first|all] [rate:=0.25] [out:=results/launch] [vehicle_params_file:=...] [ego_params_file:=...]

The CAVs are read from the bag (the first `vehicles`; the first is the ego,
or, with egos:=all, every one runs an ego in its namespace). An ego's own
encoder reaches it losslessly; the other vehicles use the codec of
vehicle_params_file. The player waits for every subscriber before playing.
Score the recording afterwards: ros2 run co3sop_nodes score OUT/graph.mcap.
"""

from pathlib import Path

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from co3sop_nodes.inference.checkpoint import DEFAULT_MODEL, read_checkpoint, resolve_checkpoint
from co3sop_nodes.ros.graph import EGOS, NodeSpec, bag_contents, describe

CONFIG = PathJoinSubstitution([FindPackageShare("co3sop_nodes"), "config"])


def nodes(context) -> list[Node]:
    arg = lambda name: LaunchConfiguration(name).perform(context)
    bag = Path(arg("bag"))
    checkpoint = str(resolve_checkpoint(arg("model"), "model"))
    cavs = bag_contents(bag)[0][: int(arg("vehicles"))]
    sensors = read_checkpoint(checkpoint)["config"]["modality"]
    graph = describe(
        bag,
        cavs,
        sensors,
        Path(arg("out")) / "graph.mcap",
        float(arg("rate")),
        egos=arg("egos"),
        common={"checkpoint": checkpoint},
    )
    files = {"ego": [arg("ego_params_file")], "vehicle": [arg("vehicle_params_file")]}

    def node(spec: NodeSpec) -> Node:
        return Node(
            package="co3sop_nodes",
            executable=spec.executable,
            prefix=" ".join(spec.prefix) or None,
            name=spec.name,
            namespace=spec.namespace or None,
            output="screen",
            arguments=list(spec.arguments),
            parameters=[*files.get(spec.executable, []), spec.parameters] if spec.parameters else None,
            remappings=list(spec.remappings) or None,
        )

    return [node(spec) for spec in (*graph.nodes, graph.player)]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [
            DeclareLaunchArgument("bag", description="a CAV bag (rosbag2 folder) to play"),
            DeclareLaunchArgument(
                "model",
                default_value=DEFAULT_MODEL,
                description="a shipped checkpoint by name (tiny-lidar, tiny) or a path",
            ),
            DeclareLaunchArgument(
                "vehicles", default_value="3", description="vehicle nodes: the bag's first CAVs; the first is the ego"
            ),
            DeclareLaunchArgument(
                "egos", default_value="first", choices=list(EGOS), description="which CAVs run an ego: first or all"
            ),
            DeclareLaunchArgument("rate", default_value="0.25", description="playback rate (1 = real time)"),
            DeclareLaunchArgument(
                "out", default_value="results/launch", description="folder of the recording graph.mcap"
            ),
            DeclareLaunchArgument(
                "vehicle_params_file",
                default_value=PathJoinSubstitution([CONFIG, "vehicle.yaml"]),
                description="the vehicles' parameters (their V2X codec)",
            ),
            DeclareLaunchArgument(
                "ego_params_file",
                default_value=PathJoinSubstitution([CONFIG, "ego.yaml"]),
                description="the ego's parameters",
            ),
            OpaqueFunction(function=nodes),
        ]
    )
