"""Topic and frame names of the Co3SOP graph and bags, defined once (documented in doc/nodes.md)."""

from __future__ import annotations

import re

# Nodes name their topics relative to their namespace (so `__ns` and remapping work); the absolute names
# below are what they resolve to in the default namespaces, as bags, recordings and tools name them.
EGO_OCCUPANCY = "/ego/occupancy"  # co3sop_msgs/SemanticOccupancy: the ego's fused prediction
EGO_POINTS = "/ego/occupancy/points"  # sensor_msgs/PointCloud2: the same, as coloured points
EGO_REQUEST = (
    "/ego/request_map"  # co3sop_msgs/RequestMap: where the ego is unsure, for the vehicles' codec (selection "request")
)
EGO_TRUTH_POINTS = (
    "/ego/ground_truth/points"  # sensor_msgs/PointCloud2: the ego's ground truth at its range (recordings only)
)
DIAGNOSTICS = "/diagnostics"  # diagnostic_msgs/DiagnosticArray: per-frame status of the ego and each vehicle
TF = "/tf"
CLOCK = "/clock"  # rosgraph_msgs/Clock: the bag's time, from the player
TF_STATIC = "/tf_static"
WORLD_FRAME = "map"
# Benchmark range -> topic suffix (as Co3SOP's label folders: additional_25m, ...)
RANGE_SUFFIX = {"25.6m": "25m", "51.2m": "50m", "76.8m": "76m"}


def relative(absolute: str) -> str:
    """The name a node in the root namespace uses for an absolute one ("/ego/occupancy" -> "ego/occupancy")."""
    return absolute.lstrip("/")


_CAV_TOPIC = re.compile(r"^/cav_(\d+)/(.+)$")


def split_cav_topic(topic: str) -> tuple[int, str] | None:
    """(vehicle id, topic relative to its namespace) of a per-vehicle topic in a bag or recording, None for any other:
    split_cav_topic("/cav_3/lidar/pose") == (3, "lidar/pose"). The one inverse of the builders below."""
    m = _CAV_TOPIC.match(topic)
    return (int(m.group(1)), m.group(2)) if m else None


def namespace(agent_id: int) -> str:
    """The default namespace of vehicle `agent_id` (`vehicle --id N` runs in it): bags put its topics under it."""
    return f"/cav_{agent_id}"


def vehicle_node(agent_id: int) -> str:
    """Fully qualified name of vehicle `agent_id`'s node in its default namespace (lifecycle and parameter services)."""
    return f"{namespace(agent_id)}/vehicle"


def _under(agent_id: int | None, name: str) -> str:
    """`name` (relative to a vehicle's namespace) under vehicle `agent_id`'s default namespace; as is for None,
    which is how the vehicle node itself names it."""
    return name if agent_id is None else f"{namespace(agent_id)}/{name}"


def voxel_features(agent_id: int | None = None) -> str:
    """co3sop_msgs/VoxelFeatures published by a vehicle's encoder."""
    return _under(agent_id, "voxel_features")


def voxel_scan(agent_id: int | None = None) -> str:
    """co3sop_msgs/VoxelScan published by a vehicle that sends its LiDAR scan in place of its features."""
    return _under(agent_id, "voxel_scan")


def local_features(agent_id: int | None = None) -> str:
    """co3sop_msgs/VoxelFeatures of a vehicle whose car also runs an ego (every CAV an ego): its features lossless,
    for that ego on board; no other car's ego subscribes to it, so it never crosses the V2X link."""
    return _under(agent_id, "voxel_features/local")


def is_local_features(topic: str) -> bool:
    return topic.endswith("/voxel_features/local")


def ego_output(absolute: str, agent_id: int | None = None) -> str:
    """An ego's output (EGO_OCCUPANCY, EGO_POINTS, EGO_REQUEST) where every CAV runs an ego: the ego of CAV
    `agent_id` runs in that CAV's namespace (/cav_3/ego/occupancy); as is for None, the one ego's."""
    return absolute if agent_id is None else namespace(agent_id) + absolute


_EGO_OCCUPANCY = re.compile(rf"^(/cav_\d+)?{re.escape(EGO_OCCUPANCY)}$")


def is_ego_occupancy(topic: str) -> bool:
    """/ego/occupancy, or an ego's of every-CAV-an-ego (/cav_N/ego/occupancy)."""
    return _EGO_OCCUPANCY.match(topic) is not None


def camera_image(agent_id: int | None, camera: str) -> str:
    """sensor_msgs/Image (rgb8) of camera0..3 (front, right, left, back)."""
    return _under(agent_id, f"{camera}/image_raw")


def camera_info(agent_id: int | None, camera: str) -> str:
    return _under(agent_id, f"{camera}/camera_info")


def camera_depth(agent_id: int | None, camera: str) -> str:
    """sensor_msgs/Image (32FC1, m) from simulated bags only."""
    return _under(agent_id, f"{camera}/depth")


def camera_semantic(agent_id: int | None, camera: str) -> str:
    """sensor_msgs/Image (mono8 labels) from simulated bags only."""
    return _under(agent_id, f"{camera}/semantic")


def lidar_points(agent_id: int | None = None) -> str:
    """sensor_msgs/PointCloud2: x, y, z, intensity (float32), label (uint8, simulated bags)."""
    return _under(agent_id, "lidar/points")


def lidar_pose(agent_id: int | None = None) -> str:
    """geometry_msgs/PoseStamped: the LiDAR's pose in the world frame."""
    return _under(agent_id, "lidar/pose")


def ground_truth(agent_id: int, range_name: str) -> str:
    """co3sop_msgs/SemanticOccupancy ground truth of one benchmark range, in the LiDAR frame."""
    return f"{namespace(agent_id)}/ground_truth/occupancy_{RANGE_SUFFIX[range_name]}"


def base_frame(agent_id: int) -> str:
    return f"cav_{agent_id}/base_link"


def lidar_frame(agent_id: int) -> str:
    return f"cav_{agent_id}/lidar"


def camera_frame(agent_id: int, camera: str) -> str:
    """Camera body frame (x along the view, z up); images are in camera_optical_frame."""
    return f"cav_{agent_id}/{camera}"


def camera_optical_frame(agent_id: int, camera: str) -> str:
    return f"cav_{agent_id}/{camera}_optical"
