"""Unit tests for co3sop_nodes.train.trainer's sample order and learning-rate schedule (no training)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from co3sop_nodes.train.trainer import learning_rate, sample_order


def test_sample_order_visits_every_sample_once_per_epoch_and_does_not_depend_on_the_step_count():
    order = sample_order(7, seed=3, steps=20)
    assert len(order) == 20
    for epoch in range(2):
        assert sorted(order[7 * epoch : 7 * epoch + 7]) == list(range(7))
    # a run resumed with more steps continues the order the longer run follows
    assert (sample_order(7, seed=3, steps=9) == order[:9]).all()
    assert not (order[:7] == order[7:14]).all()  # each epoch its own permutation
    # within one epoch: the permutation short runs have always used
    assert (sample_order(7, seed=3, steps=5) == np.random.default_rng(3).permutation(7)[:5]).all()


@pytest.mark.parametrize("steps", [1, 2, 10, 1200])
def test_cosine_decays_from_the_rate_to_zero_and_constant_stays(steps):
    rates = [learning_rate(2e-3, "cosine", k, steps) for k in range(steps)]
    assert rates[0] == 2e-3
    assert all(a >= b for a, b in zip(rates, rates[1:]))
    assert 0 <= rates[-1] <= 2e-3 * (1 - math.cos(math.pi / steps)) / 2 + 1e-12  # one step before 0
    assert {learning_rate(2e-3, "constant", k, steps) for k in range(steps)} == {2e-3}
