"""Collaborator choice (nearest first, within range, at most K) and Co3SOP pose noise."""

import numpy as np

from co3sop_nodes.v2x.neighbours import nearest_collaborators, noisy_relative


def at(x: float, y: float) -> np.ndarray:
    m = np.eye(4)
    m[:2, 3] = x, y
    return m


def test_nearest_first_within_range_at_most_k():
    candidates = {5: at(30, 0), 2: at(10, 0), 9: at(0, 80), 4: at(0, -20)}
    assert nearest_collaborators(at(0, 0), candidates) == [2, 4, 5]
    assert nearest_collaborators(at(0, 0), candidates, k=2) == [2, 4]
    assert nearest_collaborators(at(0, 0), candidates, comm_range=100) == [2, 4, 5, 9]
    assert nearest_collaborators(at(0, 0), {}, k=0) == []


def test_pose_noise_is_a_biased_planar_offset_of_the_neighbour():
    ego, other = at(0, 0), at(10, 0)
    assert np.allclose(noisy_relative(ego, other, 0.0, 0.0, np.random.default_rng(0)), np.linalg.inv(other) @ ego)
    offsets = np.array(
        [
            np.linalg.inv(noisy_relative(ego, other, 0.3, 0.02, np.random.default_rng(s)))[:3, 3] - [10, 0, 0]
            for s in range(200)
        ]
    )
    assert np.allclose(offsets[:, :2].mean(0), 0.3, atol=0.01) and np.allclose(offsets[:, :2].std(0), 0.02, atol=0.005)
    assert abs(offsets[:, 2].mean()) < 0.003 and np.isclose(offsets[:, 2].std(), 0.01, atol=0.003)
