"""One vehicle in namespace /cav_<id>: its encoder publishing /cav_<id>/voxel_features.

ros2 launch co3sop_nodes vehicle.launch.py id:=3 [checkpoint:=CKPT] [params_file:=vehicle.yaml]
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
            DeclareLaunchArgument("id", description="the vehicle's CAV id"),
            DeclareLaunchArgument(
                "checkpoint",
                default_value="",
                description="model checkpoint: a .pt file or a shipped model by name (tiny-lidar, tiny, "
                'small); "" = tiny-lidar',
            ),
            DeclareLaunchArgument(
                "params_file",
                default_value=PathJoinSubstitution([FindPackageShare("co3sop_nodes"), "config", "vehicle.yaml"]),
                description="the vehicle's parameters",
            ),
            Node(
                package="co3sop_nodes",
                executable="vehicle",
                namespace=["cav_", LaunchConfiguration("id")],
                name="vehicle",
                output="screen",
                parameters=[
                    LaunchConfiguration("params_file"),
                    {
                        "id": ParameterValue(LaunchConfiguration("id"), value_type=int),
                        "checkpoint": LaunchConfiguration("checkpoint"),
                    },
                ],
            ),
        ]
    )
