"""A rotating multi-beam LiDAR by ray casting, with CARLA's intensity model and range noise."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from co3sop_nodes import kernels
from co3sop_nodes.sim.raycast import RayScene


@dataclass(frozen=True)
class LidarConfig:
    channels: int = 64
    upper_fov: float = 2.0  # deg
    lower_fov: float = -25.0  # deg
    azimuth_steps: int = 1024  # rays per channel per sweep
    range: float = 120.0  # m
    noise_std: float = 0.02  # m, Gaussian range noise
    attenuation: float = 0.004  # CARLA's atmosphere attenuation rate, 1/m


@dataclass(frozen=True)
class LidarScan:
    points: np.ndarray  # (N, 3) float32, LiDAR frame (REP-103), m
    intensity: np.ndarray  # (N,) float32 in [0, 1]
    label: np.ndarray  # (N,) uint8 semantic label of the surface hit


def beam_directions(cfg: LidarConfig) -> np.ndarray:
    """Unit directions (channels * azimuth_steps, 3) in the LiDAR frame."""
    elevation = np.radians(np.linspace(cfg.upper_fov, cfg.lower_fov, cfg.channels))
    azimuth = np.linspace(0, 2 * np.pi, cfg.azimuth_steps, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)


def scan(scene: RayScene, world_from_lidar: np.ndarray, cfg: LidarConfig, rng: np.random.Generator) -> LidarScan:
    local = beam_directions(cfg)
    with kernels.single_threaded_blas():
        directions = local @ world_from_lidar[:3, :3].T
    hits = scene.cast(np.broadcast_to(world_from_lidar[:3, 3], directions.shape), directions, cfg.range)
    hit = np.isfinite(hits.distance)
    distance = hits.distance[hit] + rng.normal(0, cfg.noise_std, int(hit.sum()))
    points = (local[hit] * distance[:, None]).astype(np.float32)
    intensity = np.exp(-cfg.attenuation * distance).astype(np.float32)
    labels = np.array([o.label for o in scene.objects], np.uint8)[hits.object_index[hit]]
    return LidarScan(points, intensity, labels)
