"""Co3SOP collaborative 3D semantic occupancy prediction on ROS 2.

Everything at this level is ROS-free (no rclpy, no generated messages); the
`ros` subpackage is the only glue to ROS 2.
"""
