"""IoU / mIoU in the three conventions, on hand-made grids with hand-computed answers."""

import numpy as np
import pytest

from co3sop_nodes.classes import IGNORE, LABEL_BY_NAME as L
from co3sop_nodes.metrics import Confusion, markdown_table


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
