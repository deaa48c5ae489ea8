"""OccFormer's training loss: Mask2Former-style mask classification with Hungarian matching.

Per sample, the ground truth is one binary mask per class present (empty
included; 255 is ignored). Masks are compared on points drawn by class-guided
sampling: without replacement, each labelled voxel with weight
(f_min / f_class)^0.25 by its class's voxel count in the sample, so rare
classes are not drowned by empty space (OccFormer weighs by dataset
frequencies; the sample's own counts need no dataset statistics). For the
prediction of every decoder layer (deep supervision), the queries are matched
one to one to the ground-truth masks at the least cost
2 x (-p(class)) + 5 x BCE + 5 x dice, then the loss is
2 x cross-entropy of every query's class (unmatched: "no object", weight 0.1)
+ 5 x BCE + 5 x dice of the matched masks. (OccFormer also supervises LSS
depth; our lifting has no depth bins. It uses no scene-class affinity terms.)
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from co3sop_nodes.model.losses import IGNORE
from co3sop_nodes.model.matching import min_cost_assignment
from co3sop_nodes.model.occformer import masks_at

CLASS_WEIGHT, MASK_WEIGHT, DICE_WEIGHT, NO_OBJECT_WEIGHT = 2.0, 5.0, 5.0, 0.1
GAMMA = 0.25


def class_guided_points(labels: torch.Tensor, count: int, rng: np.random.Generator) -> torch.Tensor:
    """labels (X, Y, Z) -> up to `count` flat indices of labelled voxels, drawn without replacement with weights
    (f_min / f_class)^GAMMA (Gumbel top-k: keys log w + Gumbel noise, the largest `count`)."""
    flat = labels.flatten()
    valid = torch.nonzero(flat != IGNORE)[:, 0]
    classes = flat[valid]
    counts = torch.bincount(classes).float()
    weight = (counts[counts > 0].min() / counts.clamp_min(1)) ** GAMMA  # (K,)
    u = torch.from_numpy(rng.random(len(valid))).to(weight.device).clamp_min(1e-12)
    keys = weight[classes].log() - torch.log(-torch.log(u))
    return valid[torch.topk(keys, min(count, len(valid))).indices]


def _bce_cost(m: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean binary cross-entropy of every mask (Q, N) logits against every target (G, N) 0/1 -> (Q, G)."""
    return (F.softplus(-m) @ gt.T + F.softplus(m) @ (1 - gt).T) / m.shape[1]


def _dice_cost(m: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    p = m.sigmoid()
    return 1 - (2 * p @ gt.T + 1) / (p.sum(1)[:, None] + gt.sum(1)[None] + 1)


def mask_classification_loss(
    preds: list[tuple[torch.Tensor, torch.Tensor]], labels: torch.Tensor, points: int, rng: np.random.Generator
) -> dict[str, torch.Tensor]:
    """preds: every decoder output (class logits (B, Q, K+1), mask logits (B, Q, x, y, z) at 1/4); labels (B, X, Y, Z)
    with 255 ignored -> the loss terms summed over decoder outputs, mean over the batch."""
    b, k = labels.shape[0], preds[0][0].shape[-1] - 1
    dims = tuple(labels.shape[1:])
    weights = torch.ones(k + 1, device=labels.device)
    weights[k] = NO_OBJECT_WEIGHT
    parts = {"mask ce": 0.0, "mask bce": 0.0, "mask dice": 0.0}
    for s in range(b):
        index = class_guided_points(labels[s], points, rng)  # (N,)
        at = labels[s].flatten()[index]  # (N,)
        present = torch.unique(at)  # (G,)
        gt = (at[None] == present[:, None]).float()  # (G, N)
        for logits, masks in preds:
            m = masks_at(masks[s : s + 1], index[None], dims)[0]  # (Q, N)
            with torch.no_grad():
                cost = (
                    CLASS_WEIGHT * -logits[s].softmax(-1)[:, present]
                    + MASK_WEIGHT * _bce_cost(m, gt)
                    + DICE_WEIGHT * _dice_cost(m, gt)
                )
                rows, cols = (torch.from_numpy(a).to(labels.device) for a in min_cost_assignment(cost.cpu().numpy()))
            target = torch.full((logits.shape[1],), k, dtype=torch.long, device=labels.device)
            target[rows] = present[cols]
            parts["mask ce"] = parts["mask ce"] + CLASS_WEIGHT * F.cross_entropy(logits[s], target, weight=weights) / b
            matched, goal = m[rows], gt[cols]
            parts["mask bce"] = parts["mask bce"] + MASK_WEIGHT * F.binary_cross_entropy_with_logits(matched, goal) / b
            p = matched.sigmoid()
            dice = 1 - (2 * (p * goal).sum(1) + 1) / (p.sum(1) + goal.sum(1) + 1)
            parts["mask dice"] = parts["mask dice"] + DICE_WEIGHT * dice.mean() / b
    return parts
