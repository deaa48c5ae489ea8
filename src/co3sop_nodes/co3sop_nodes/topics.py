"""Topic names of the Co3SOP graph, defined once (documented in README.md)."""

EGO_OCCUPANCY = "/ego/occupancy"  # co3sop_msgs/SemanticOccupancy: the ego's fused prediction


def voxel_features(agent_id: int) -> str:
    """co3sop_msgs/VoxelFeatures published by vehicle `agent_id`'s encoder."""
    return f"/cav_{agent_id}/voxel_features"
