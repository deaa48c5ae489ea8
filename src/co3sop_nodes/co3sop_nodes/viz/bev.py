"""Bird's-eye-view pictures of label grids in the paper's palette (ROS-free)."""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.classes import CLASS_NAMES, EMPTY, IGNORE, PALETTE


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


def save_comparison(truth: np.ndarray, prediction: np.ndarray, path, title: str, voxel_size: float) -> list[str]:
    """Ground truth beside prediction as bird's-eye views, with panel titles, metre axes (x forward up, y left to
    the left, the ego at the centre) and a legend of the classes either shows, written to `path` (PNG); the
    figure's texts (title, panel titles, legend entries)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    half_x, half_y = truth.shape[0] * voxel_size / 2, truth.shape[1] * voxel_size / 2
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.6), constrained_layout=True)
    for ax, labels, name in zip(axes, (truth, prediction), ("ground truth", "prediction")):
        ax.imshow(bev_image(labels), extent=(half_y, -half_y, -half_x, half_x), interpolation="nearest")
        ax.set_title(name)
        ax.set_xlabel("y (m, left)")
        ax.set_ylabel("x (m, forward)")
        ax.plot([0], [0], marker="^", color="black", markersize=6)  # the ego's LiDAR
    shown = sorted((set(np.unique(bev_labels(truth))) | set(np.unique(bev_labels(prediction)))) - {EMPTY, IGNORE})
    handles = [Patch(color=PALETTE[c] / 255, label=f"{c} {CLASS_NAMES[c]}") for c in shown]
    fig.legend(handles=handles, loc="outside right center", fontsize=8, title="class (topmost voxel)")
    fig.suptitle(title)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return [title, *(ax.get_title() for ax in axes), *(h.get_label() for h in handles)]
