"""The procedural OPV2V-style simulator: towns, traffic, sensors, the semantic voxel sensor, outputs (ROS-free)."""
