"""Command-line tools (console scripts of co3sop_nodes; ROS-free)."""
