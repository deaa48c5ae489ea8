"""The byte budget of a rate-limited link (v2x/sender_budget.py) and the codec settings that ask for it."""

from __future__ import annotations

import numpy as np
import pytest

from co3sop_nodes.common.errors import CodecError
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.v2x.codec import FeatureCodecConfig, encode_features
from co3sop_nodes.v2x.sender_budget import ByteBudget, SenderBudgets, budget_for


def test_unspent_bytes_carry_over_up_to_the_burst():
    budget = ByteBudget(rate=100, burst=250)
    assert budget.allowance() == 250  # full to start with, as tc tbf's bucket
    budget.spend(250)
    assert budget.allowance() == 100
    budget.spend(40)
    assert budget.allowance() == 160
    budget.spend(0)
    assert budget.allowance() == 250  # 100 + 160 saved, capped at the burst


@pytest.mark.parametrize("seed", range(5))
def test_no_run_of_messages_takes_more_than_a_burst_beyond_its_average(seed):
    rng = np.random.default_rng(seed)
    budget = ByteBudget(rate=1000, burst=int(rng.integers(1000, 5000)))
    sizes = []
    for _ in range(200):
        allowance = budget.allowance()
        assert allowance <= budget.burst
        sizes.append(int(rng.integers(allowance // 2, allowance + 1)))
        budget.spend(sizes[-1])
    for start in range(0, 200, 7):
        for n in (1, 5, 50):
            assert sum(sizes[start : start + n]) <= budget.burst + (n - 1) * budget.rate
    assert sum(sizes) / len(sizes) <= budget.rate + (budget.burst - budget.rate) / len(sizes)


def test_overspending_is_an_error():
    budget = ByteBudget(rate=100, burst=200)
    with pytest.raises(CodecError, match="220 bytes overspends its allowance of 200"):
        budget.spend(220)


def test_a_codec_with_a_burst_gets_a_budget_and_one_without_does_not():
    assert budget_for(FeatureCodecConfig("int8", "request", max_bytes=65536)) is None
    budget = budget_for(FeatureCodecConfig("int8", "request", max_bytes=65536, burst_bytes=131072))
    assert (budget.rate, budget.burst, budget.allowance()) == (65536, 131072, 131072)
    budget.spend(131072 - 1000)
    cfg = budget.config(FeatureCodecConfig("int8", "request", max_bytes=65536, burst_bytes=131072, rank=8))
    assert (cfg.max_bytes, cfg.burst_bytes, cfg.rank) == (65536 + 1000, 131072, 8)


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"burst_bytes": 1024}, "needs a max_bytes budget"),
        ({"max_bytes": 4096, "burst_bytes": 1024}, "needs a max_bytes budget of at most it"),
        ({"max_bytes": 4096, "burst_bytes": -1}, "whole number of bytes"),
        ({"max_bytes": 4096, "burst_bytes": True}, "whole number of bytes"),
    ],
)
def test_bad_bursts_are_refused_naming_the_field(kw, match):
    with pytest.raises(CodecError, match=match):
        FeatureCodecConfig("int8", "request", **kw)


def test_a_large_frame_takes_what_small_ones_left():
    """Request maps under a 4 KB average: a frame asking for little leaves bytes a later, larger one spends (after a
    first message that emptied the bucket)."""
    grid = GridSpec((0.0, 0.0, 0.0), 1.0, (16, 16, 4))
    rng = np.random.default_rng(0)
    features = rng.normal(size=(8, *grid.dims)).astype(np.float32)
    confidence = rng.uniform(size=grid.dims).astype(np.float32)
    small, large = np.zeros(grid.dims, np.float32), np.ones(grid.dims, np.float32)
    small[:2] = 1.0
    cfg = FeatureCodecConfig("int8", "request", max_bytes=4096, burst_bytes=12288)
    assert cfg.name == "int8-request4KB-burst12KB-zstd"
    capped = encode_features(features, confidence, grid, FeatureCodecConfig("int8", "request", max_bytes=4096), large)
    budget, sizes = budget_for(cfg), []
    budget.spend(budget.allowance())
    for request in (small, small, large):
        enc = encode_features(features, confidence, grid, budget.config(cfg), request)
        budget.spend(enc.budget_bytes)
        sizes.append(enc.budget_bytes)
    assert sizes[0] < 4096 and sizes[1] < 4096
    assert 4096 < sizes[2] <= 12288
    assert sum(sizes) <= 3 * 4096
    assert capped.budget_bytes <= 4096 < sizes[2]


def test_a_receiver_that_joins_later_starts_where_the_messages_for_all_left_its_budget():
    budgets = SenderBudgets(FeatureCodecConfig("int8", "request", max_bytes=100, burst_bytes=400))
    everyone = budgets.of(None)
    everyone.spend(400)  # the first message, for every receiver: the whole bucket
    assert budgets.of(None) is everyone and everyone.allowance() == 100
    late = budgets.of(7)  # its first own message: no second burst
    assert late is not everyone and late.allowance() == 100
    late.spend(10)
    assert everyone.allowance() == 100 and budgets.of(7).allowance() == 190
    assert budgets.config(7).max_bytes == 190
    budgets.spend(7, 190)
    assert budgets.config(7).max_bytes == 100
    capped = SenderBudgets(FeatureCodecConfig("int8", "request", max_bytes=100))  # each message capped alone
    assert capped.of(3) is None and capped.config(3) is capped.cfg
    capped.spend(3, 100)
    assert capped.config(3).max_bytes == 100
