"""Poses and frames (ROS-free).

Every pose in this package is in REP-103 axes (x forward, y left, z up;
right-handed), as in ROS messages.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Pose:
    """A rigid pose: position in m, orientation as a unit quaternion (x, y, z, w)."""

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
