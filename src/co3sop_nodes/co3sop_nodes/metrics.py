"""Semantic occupancy metrics: per-class IoU and mIoU in the three conventions peers use (ROS-free).

Counts accumulate over a dataset (equivalent to Co3SOP's per-sample averaging
of tp / gt / pred). Voxels labelled 255 in the ground truth are ignored.

- "co3sop-readme": mean IoU over all 24 classes including empty; the Co3SOP
  README's numbers follow it (17 of 18 rows).
- "co3sop-code": mean over classes 1..23 (empty excluded), Co3SOP's code.
  Both Co3SOP conventions count a class absent from ground truth and
  prediction as IoU 0, as Co3SOP's code does.
- "surroundocc": geometry IoU (occupied vs empty) and mean over the semantic
  classes 1..23 that occur in the ground truth (absent classes are left out).
"""

from __future__ import annotations

import numpy as np

from .classes import CLASS_NAMES, EMPTY, IGNORE, NUM_CLASSES

CONVENTIONS = ("co3sop-readme", "co3sop-code", "surroundocc")


class Confusion:
    """Per-class true positives, ground-truth and predicted voxel counts, and the same for geometry."""

    def __init__(self, classes: int = NUM_CLASSES):
        self.classes = classes
        self.tp = np.zeros(classes, np.int64)
        self.gt = np.zeros(classes, np.int64)
        self.pred = np.zeros(classes, np.int64)
        self.geo = np.zeros(3, np.int64)  # tp, gt, pred of occupied vs empty
        self.frames = 0

    def add(self, prediction: np.ndarray, truth: np.ndarray) -> None:
        """prediction, truth: label grids of one frame (same shape)."""
        valid = truth != IGNORE
        p, t = prediction[valid].astype(np.int64), truth[valid].astype(np.int64)
        self.tp += np.bincount(t[p == t], minlength=self.classes)[: self.classes]
        self.gt += np.bincount(t, minlength=self.classes)[: self.classes]
        self.pred += np.bincount(p, minlength=self.classes)[: self.classes]
        po, to = p != EMPTY, t != EMPTY
        self.geo += [int((po & to).sum()), int(to.sum()), int(po.sum())]
        self.frames += 1

    def iou(self) -> np.ndarray:
        """(K,) IoU per class; NaN where the class is in neither ground truth nor prediction."""
        union = self.gt + self.pred - self.tp
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(union > 0, self.tp / np.maximum(union, 1), np.nan)

    def summary(self) -> dict:
        iou = self.iou()
        zero_absent = np.nan_to_num(iou, nan=0.0)
        present = self.gt[1:] > 0
        tp, gt, pred = self.geo
        return {
            "frames": self.frames,
            "per_class_iou": {CLASS_NAMES[c]: (None if np.isnan(iou[c]) else float(iou[c])) for c in range(self.classes)},
            "co3sop-readme": {"miou": float(zero_absent.mean())},
            "co3sop-code": {"miou": float(zero_absent[1:].mean())},
            "surroundocc": {"iou": float(tp / max(gt + pred - tp, 1)),
                            "miou": float(iou[1:][present].mean()) if present.any() else float("nan")},
        }


def markdown_table(results: dict[str, dict]) -> str:
    """Per-class IoU (%) and mIoU in the three conventions; one column per named result."""
    names = list(results)
    lines = ["| class | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for c, cls in enumerate(CLASS_NAMES):
        cells = [results[n]["per_class_iou"][cls] for n in names]
        if all(v is None for v in cells):
            continue
        lines.append(f"| {c} {cls} | " + " | ".join("-" if v is None else f"{100 * v:.2f}" for v in cells) + " |")
    lines.append("| **mIoU co3sop-readme** (24 incl. empty) | " + " | ".join(f"**{100 * results[n]['co3sop-readme']['miou']:.2f}**" for n in names) + " |")
    lines.append("| **mIoU co3sop-code** (1..23) | " + " | ".join(f"**{100 * results[n]['co3sop-code']['miou']:.2f}**" for n in names) + " |")
    lines.append("| **mIoU surroundocc** (present 1..23) | " + " | ".join(f"**{100 * results[n]['surroundocc']['miou']:.2f}**" for n in names) + " |")
    lines.append("| IoU geometry (surroundocc) | " + " | ".join(f"{100 * results[n]['surroundocc']['iou']:.2f}" for n in names) + " |")
    return "\n".join(lines)
