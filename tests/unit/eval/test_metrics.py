"""IoU / mIoU in the three conventions, on hand-made grids with hand-computed answers."""

import numpy as np
import pytest

from co3sop_nodes.common.classes import IGNORE
from co3sop_nodes.common.classes import LABEL_BY_NAME as L
from co3sop_nodes.eval.metrics import (
    SCORES,
    Bootstrap,
    Confusion,
    confusions_of,
    difference_table,
    markdown_table,
    point,
    pooled,
    scores,
)


def grids():
    truth = np.zeros((2, 2, 2), np.uint8)
    pred = np.zeros((2, 2, 2), np.uint8)
    truth[0, 0, :] = L["road"]  # 2 road voxels
    truth[1, 1, 1] = L["vehicle"]  # 1 vehicle voxel
    truth[1, 0, 0] = IGNORE  # not scored
    pred[0, 0, 0] = L["road"]  # one road right
    pred[0, 0, 1] = L["vehicle"]  # one road called vehicle
    pred[1, 1, 1] = L["vehicle"]  # the vehicle right
    pred[1, 0, 0] = L["building"]  # on an ignored voxel: not counted
    return pred, truth


def test_per_class_iou_by_hand():
    c = Confusion()
    c.add(*grids())
    iou = c.iou()
    assert iou[L["road"]] == pytest.approx(1 / 2)  # tp 1, gt 2, pred 1
    assert iou[L["vehicle"]] == pytest.approx(1 / 2)  # tp 1, gt 1, pred 2
    assert iou[0] == pytest.approx(4 / 4)  # empty: 4 right, no confusion
    assert np.isnan(iou[L["building"]])  # only predicted on an ignored voxel: never counted
    assert np.isnan(iou[L["pole"]])


def test_three_conventions_by_hand():
    c = Confusion()
    c.add(*grids())
    s = c.summary()
    assert s["co3sop-readme"]["miou"] == pytest.approx((1 + 0.5 + 0.5) / 24)  # absent classes count 0
    assert s["co3sop-code"]["miou"] == pytest.approx((0.5 + 0.5) / 23)  # empty excluded
    assert s["surroundocc"]["miou"] == pytest.approx(0.5)  # only classes in the ground truth
    assert s["surroundocc"]["iou"] == pytest.approx(3 / 3)  # occupied voxels: 3 true, 3 predicted, all overlap
    assert s["frames"] == 1


def test_counts_accumulate_like_one_big_frame():
    pred, truth = grids()
    one = Confusion()
    one.add(np.concatenate([pred, pred]), np.concatenate([truth, truth]))
    two = Confusion()
    two.add(pred, truth)
    two.add(pred, truth)
    np.testing.assert_array_equal(one.tp, two.tp)
    np.testing.assert_array_equal(one.iou(), two.iou())


def test_markdown_table_lists_present_classes_and_all_conventions():
    c = Confusion()
    c.add(*grids())
    text = markdown_table({"51.2m": c.summary()})
    assert "| 7 road | 50.00 |" in text and "| 10 vehicle | 50.00 |" in text
    assert "pole" not in text
    for name in ("co3sop-readme", "co3sop-code", "surroundocc"):
        assert f"mIoU {name}" in text


# --- bootstrap intervals over scenarios ---------------------------------------------------------


def scenario_confusions(seed: int, scenarios: int = 6, hit_rate: float = 0.7) -> dict:
    """Per-scenario confusions of random grids whose predictions are right with probability hit_rate."""
    rng = np.random.default_rng(seed)
    out = {}
    for s in range(scenarios):
        truth = rng.choice([0, L["road"], L["vehicle"], L["building"]], size=(8, 8, 4), p=[0.6, 0.2, 0.1, 0.1]).astype(
            np.uint8
        )
        noise = rng.integers(0, 4, size=truth.shape).astype(np.uint8)
        pred = np.where(rng.random(truth.shape) < hit_rate, truth, noise)
        c = Confusion()
        c.add(pred, truth)
        out[f"test/s{s}"] = c
    return out


def test_scores_of_stacked_counts_equal_each_summary():
    runs = scenario_confusions(0)
    stacked = scores(*(np.stack([getattr(c, a) for c in runs.values()]) for a in ("tp", "gt", "pred", "geo")))
    for i, c in enumerate(runs.values()):
        s = c.summary()
        for name in SCORES:
            assert stacked[name][i] == pytest.approx(point(s, name))


def test_bootstrap_interval_holds_the_pooled_estimate_and_each_draw_resamples_every_scenario():
    runs = scenario_confusions(1)
    boot = Bootstrap(list(runs), draws=500, seed=0)
    assert (boot.counts.sum(axis=1) == len(runs)).all()
    summary = boot.summary(runs)
    assert summary["scenarios"] == len(runs)
    assert summary["co3sop-code"]["miou"] == pytest.approx(pooled(runs).summary()["co3sop-code"]["miou"])
    for name in SCORES:
        low, high = summary["ci95"][name]
        assert low <= point(summary, name) <= high
        assert high > low  # scenarios differ: a real spread


def test_identical_scenarios_give_a_zero_width_interval():
    one = scenario_confusions(2, scenarios=1)["test/s0"]
    runs = {f"test/s{i}": one for i in range(5)}
    low, high = Bootstrap(list(runs), draws=200).interval(runs)["co3sop-readme"]
    assert low == pytest.approx(high)


def test_paired_difference_is_zero_against_itself_and_positive_for_a_better_run():
    worse, better = (
        scenario_confusions(3, hit_rate=0.5),
        scenario_confusions(3, hit_rate=0.9),
    )  # same truths per scenario
    boot = Bootstrap(list(worse), draws=500)
    same = boot.difference(worse, worse)
    assert all(same[n]["delta"] == 0 and same[n]["ci95"] == [0.0, 0.0] for n in SCORES)
    gain = boot.difference(better, worse)
    assert gain["co3sop-code"]["delta"] > 0 and gain["co3sop-code"]["ci95"][0] > 0
    # the paired interval is narrower than the difference of the two unpaired ones would suggest
    lo_b, hi_b = boot.interval(better)["co3sop-code"]
    lo_w, hi_w = boot.interval(worse)["co3sop-code"]
    assert gain["co3sop-code"]["ci95"][1] - gain["co3sop-code"]["ci95"][0] < (hi_b - lo_b) + (hi_w - lo_w)


def test_gain_ratios_share_one_reference_gain():
    alone, mid, full = (scenario_confusions(4, hit_rate=h) for h in (0.5, 0.7, 0.9))  # same truths per scenario
    boot = Bootstrap(list(alone), draws=300)
    kept = boot.ratio(mid, full, alone)
    assert 0 < kept["ratio"] < 1 and kept["ci95"][0] <= kept["ratio"] <= kept["ci95"][1]
    assert boot.gain_ratio(mid, alone, full, alone) == kept  # the same base on both sides: ratio itself
    # a run measured against its own better base keeps less of the same reference gain
    own = boot.gain_ratio(full, mid, full, alone)
    assert own["ratio"] == pytest.approx(1 - kept["ratio"])
    assert boot.gain_ratio(full, full, full, alone)["ratio"] == 0


def test_bootstrap_refuses_a_run_without_every_scenario():
    runs = scenario_confusions(4)
    boot = Bootstrap(list(runs) + ["test/missing"], draws=10)
    with pytest.raises(ValueError, match="missing"):
        boot.interval(runs)


def test_tables_show_intervals_and_differences():
    runs = scenario_confusions(5)
    boot = Bootstrap(list(runs), draws=100)
    text = markdown_table({"a": boot.summary(runs)})
    assert "| 95 % interval co3sop-code | [" in text and "| scenarios | 6 |" in text
    diff = difference_table({"b": boot.difference(runs, runs)}, "a")
    assert "| b | +0.00 [0.00, 0.00] |" in diff


def test_per_scenario_counts_round_trip_through_json():
    import json

    runs = scenario_confusions(6)
    boot = Bootstrap(list(runs), draws=50)
    summary = json.loads(json.dumps(boot.summary(runs)))
    back = confusions_of(summary)
    assert boot.difference(back, runs)["co3sop-code"] == {"delta": 0.0, "ci95": [0.0, 0.0]}
    assert boot.summary(back)["ci95"] == summary["ci95"]
