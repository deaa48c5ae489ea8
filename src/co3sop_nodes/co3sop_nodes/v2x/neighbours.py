"""Who the ego collaborates with, and how their poses are perturbed in the pose-noise study (ROS-free).

Shared by the dataset, offline evaluation and the ego node, so all three pick
the same collaborators in the same order and align them the same way.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

COMM_RANGE = 70.0  # m, OpenCOOD's default communication range


def nearest_collaborators(
    world_from_ego: np.ndarray,
    candidates: Mapping[int, np.ndarray],
    comm_range: float = COMM_RANGE,
    k: int | None = None,
) -> list[int]:
    """Ids of the candidates (id -> world_from_lidar) within `comm_range` m of the ego (x, y), nearest first, at most k."""
    dist = {i: float(np.linalg.norm(m[:2, 3] - world_from_ego[:2, 3])) for i, m in candidates.items()}
    chosen = sorted((d, i) for i, d in dist.items() if d <= comm_range)
    return [i for _, i in chosen][:k]


def noisy_relative(
    world_from_ego: np.ndarray, world_from_other: np.ndarray, mu: float, sigma: float, rng: np.random.Generator
) -> np.ndarray:
    """neighbour_from_ego after Co3SOP's pose noise on the neighbour's world pose.

    Neighbours only: dx, dy ~ N(mu, sigma) (a biased offset), dz ~ N(0, 0.01).
    """
    noisy = world_from_other.copy()
    if mu or sigma:
        noisy[:2, 3] += rng.normal(mu, sigma, 2)
        noisy[2, 3] += rng.normal(0.0, 0.01)
    return np.linalg.inv(noisy) @ world_from_ego
