"""The 24 Co3SOP labels: names, CARLA 0.9.12 tags, and the paper's palette.

Label 0 is empty (free space); labels 1..22 are the CARLA 0.9.10-0.9.13
semantic tags 1..22; label 23 is CARLA's tag 0 (unlabeled). 255 marks voxels
that are ignored in losses and metrics. CARLA 0.9.14+ renumbers its tags:
never mix them with these.
"""

from __future__ import annotations

import numpy as np

EMPTY = 0
UNLABELED = 23
IGNORE = 255
NUM_CLASSES = 24

# (name, RGB) per label, in label order; colours from the paper's \definecolor list.
_CLASSES: tuple[tuple[str, tuple[int, int, int]], ...] = (
    ("empty", (0, 0, 0)),
    ("building", (70, 70, 70)),
    ("fence", (190, 153, 153)),
    ("other", (55, 90, 80)),
    ("pedestrian", (220, 20, 60)),
    ("pole", (153, 153, 153)),
    ("roadline", (157, 234, 50)),
    ("road", (128, 64, 128)),
    ("sidewalk", (244, 35, 232)),
    ("vegetation", (107, 142, 35)),
    ("vehicle", (0, 0, 142)),
    ("wall", (102, 102, 156)),
    ("trafficsign", (220, 220, 0)),
    ("sky", (70, 130, 180)),
    ("ground", (81, 0, 81)),
    ("bridge", (150, 100, 100)),
    ("railtrack", (230, 150, 140)),
    ("guardrail", (180, 165, 180)),
    ("trafficlight", (250, 170, 30)),
    ("static", (110, 190, 160)),
    ("dynamic", (170, 120, 50)),
    ("water", (45, 60, 150)),
    ("terrain", (145, 170, 100)),
    ("unlabeled", (160, 60, 60)),
)

CLASS_NAMES: tuple[str, ...] = tuple(name for name, _ in _CLASSES)
PALETTE = np.array([rgb for _, rgb in _CLASSES], dtype=np.uint8)  # (24, 3)

LABEL_BY_NAME: dict[str, int] = {name: label for label, name in enumerate(CLASS_NAMES)}
