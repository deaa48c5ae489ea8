"""Bird's-eye-view pictures of label grids in the paper's palette (ROS-free)."""

from __future__ import annotations

import numpy as np

from .classes import EMPTY, IGNORE, PALETTE


def bev_labels(labels: np.ndarray) -> np.ndarray:
    """(nx, ny, nz) labels -> (nx, ny) label of the topmost occupied voxel per column (0 where none)."""
    occupied = (labels != EMPTY) & (labels != IGNORE)
    top = labels.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)  # (nx, ny)
    column = np.take_along_axis(labels, top[:, :, None], axis=2)[:, :, 0]
    return np.where(occupied.any(axis=2), column, EMPTY)


def bev_image(labels: np.ndarray, scale: int = 1) -> np.ndarray:
    """(nx, ny, nz) labels -> (H, W, 3) uint8 RGB, x (forward) up and y (left) to the left."""
    top = bev_labels(labels)[::-1, ::-1]  # rows: decreasing x; columns: decreasing y
    rgb = PALETTE[np.minimum(top, len(PALETTE) - 1)]
    rgb[top == IGNORE] = (255, 255, 255)
    return np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1)
