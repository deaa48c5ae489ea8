"""The ROS 2 glue: nodes, their parameters and DDS settings, the graph the demo launches.

Importing it sets the process's malloc up for nodes (`common.allocation.keep_freed_memory`) before numpy and rclpy
start their threads: glibc settles which arena a thread allocates from when the thread starts, and a node's
threads share one only if it is set before.
"""

from co3sop_nodes.common.allocation import keep_freed_memory

keep_freed_memory()
