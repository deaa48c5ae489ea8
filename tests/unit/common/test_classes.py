"""Unit tests for co3sop_nodes.common.classes: the 24 labels and the paper's palette."""

from __future__ import annotations

import numpy as np
import pytest

from co3sop_nodes.common import classes


def test_24_classes():
    assert classes.NUM_CLASSES == 24
    assert len(classes.CLASS_NAMES) == 24
    assert len(set(classes.CLASS_NAMES)) == 24


def test_special_labels():
    assert classes.EMPTY == 0 and classes.CLASS_NAMES[0] == "empty"
    assert classes.UNLABELED == 23 and classes.CLASS_NAMES[23] == "unlabeled"
    assert classes.IGNORE == 255 and classes.IGNORE >= classes.NUM_CLASSES


def test_carla_tag_order():
    # labels 1..22 are CARLA 0.9.12 tags 1..22 (Building ... Terrain)
    assert classes.CLASS_NAMES[1] == "building"
    assert classes.CLASS_NAMES[7] == "road"
    assert classes.CLASS_NAMES[10] == "vehicle"
    assert classes.CLASS_NAMES[22] == "terrain"


def test_palette_shape_and_dtype():
    assert classes.PALETTE.shape == (24, 3)
    assert classes.PALETTE.dtype == np.uint8


@pytest.mark.parametrize(
    "name,rgb",
    [
        ("empty", (0, 0, 0)),
        ("fence", (190, 153, 153)),
        ("road", (128, 64, 128)),
        ("unlabeled", (160, 60, 60)),
        ("vehicle", (0, 0, 142)),
        ("vegetation", (107, 142, 35)),
    ],
)
def test_spot_colours(name, rgb):
    label = classes.LABEL_BY_NAME[name]
    assert tuple(int(c) for c in classes.PALETTE[label]) == rgb


def test_palette_colours_are_distinct():
    assert len({tuple(row) for row in classes.PALETTE.tolist()}) == 24


def test_label_by_name_inverts_names():
    assert len(classes.LABEL_BY_NAME) == 24
    for label, name in enumerate(classes.CLASS_NAMES):
        assert classes.LABEL_BY_NAME[name] == label


def test_palette_colours_a_label_grid():
    labels = np.array([[0, 2], [7, 23]], np.uint8)
    rgb = classes.PALETTE[labels]
    assert rgb.shape == (2, 2, 3) and rgb.dtype == np.uint8
    assert rgb[1, 0].tolist() == [128, 64, 128]
