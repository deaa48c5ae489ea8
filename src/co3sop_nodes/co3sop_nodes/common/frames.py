"""One CAV's data at one timestamp, in REP-103 frames (ROS-free).

The simulator produces these, the OPV2V folder writer/reader turns them into
and back from OPV2V/Co3SOP files (converting CARLA axes at that boundary), and
the bag writer turns them into ROS messages. World poses are 4x4 world_from_x.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime

import numpy as np


@dataclass
class CameraFrame:
    name: str  # "camera0".."camera3"
    world_from_camera: np.ndarray  # (4, 4) camera body frame: x along the view, y left, z up
    intrinsics: np.ndarray  # (3, 3) pinhole matrix of `rgb`
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray | None = None  # (H, W) float32 m, 0 = nothing hit (simulator only)
    semantic: np.ndarray | None = None  # (H, W) uint8 labels (simulator only)


@dataclass
class OtherVehicle:
    id: int
    world_from_vehicle: np.ndarray  # (4, 4) actor origin (ground, box centre)
    center: np.ndarray  # (3,) bounding box centre in the actor frame, m
    extent: np.ndarray  # (3,) half sizes, m
    speed: float  # m/s


@dataclass
class CavFrame:
    scenario: str
    cav_id: int
    timestamp: int  # OPV2V frame key ('%06d' in file names); 10 Hz data steps by 2
    world_from_vehicle: np.ndarray  # (4, 4) true vehicle pose
    world_from_lidar: np.ndarray  # (4, 4) LiDAR pose
    speed: float  # m/s
    cameras: list[CameraFrame]
    points: np.ndarray  # (N, 3) float32 LiDAR frame, m
    intensity: np.ndarray  # (N,) float32 in [0, 1]
    point_labels: np.ndarray | None = None  # (N,) uint8 (simulator only)
    labels: dict[str, np.ndarray] = field(default_factory=dict)  # benchmark range -> (nx, ny, nz) uint8, LiDAR frame
    vehicles: list[OtherVehicle] = field(default_factory=list)  # actors around this CAV
    plan: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3) world x, y (m), target speed (m/s)
    world_from_predicted: np.ndarray | None = None  # (4, 4) localisation estimate (GNSS); None: the true pose

    @property
    def stamp_ns(self) -> int:
        """Sensor time: OPV2V frames tick at 20 Hz (0.05 s) from the scenario's start."""
        return scenario_epoch_ns(self.scenario) + self.timestamp * 50_000_000


def scenario_epoch_ns(scenario: str) -> int:
    """Start time of a scenario named as OPV2V's ('%Y_%m_%d_%H_%M_%S', UTC); 0 for other names."""
    try:
        start = datetime.strptime(scenario, "%Y_%m_%d_%H_%M_%S").replace(tzinfo=UTC)
    except ValueError:
        return 0
    return int(start.timestamp()) * 1_000_000_000
