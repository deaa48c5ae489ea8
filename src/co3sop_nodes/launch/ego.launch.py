"""The ego: fuses its own and its neighbours' features, publishes /ego/occupancy.

ros2 launch co3sop_nodes ego.launch.py ego_id:=3 [checkpoint:=CKPT] [params_file:=ego.yaml]
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [
            DeclareLaunchArgument("ego_id", description="which vehicle is the ego"),
            DeclareLaunchArgument(
                "checkpoint",
                default_value="",
                description="model checkpoint (the vehicles'): a .pt file or a shipped model by name "
                '(tiny-lidar, tiny, small); "" = tiny-lidar',
            ),
            DeclareLaunchArgument(
                "params_file",
                default_value=PathJoinSubstitution([FindPackageShare("co3sop_nodes"), "config", "ego.yaml"]),
                description="the ego's parameters",
            ),
            Node(
                package="co3sop_nodes",
                executable="ego",
                name="ego",
                output="screen",
                parameters=[
                    LaunchConfiguration("params_file"),
                    {
                        "ego_id": ParameterValue(LaunchConfiguration("ego_id"), value_type=int),
                        "checkpoint": LaunchConfiguration("checkpoint"),
                    },
                ],
            ),
        ]
    )
