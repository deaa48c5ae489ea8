"""Losses: cross-entropy (ignore 255) + scene-class affinity (sem_scal, geo_scal) per scale, plus confidence.

Affinity losses (MonoScene): over the voxels not ignored, with p the softmax,
for a class c present in the ground truth: precision P = sum(p_c [y=c]) /
sum(p_c), recall R = sum(p_c [y=c]) / sum([y=c]), specificity S =
sum((1 - p_c)[y!=c]) / sum([y!=c]); sem_scal averages l(P) + l(R) + l(S) over
those classes, geo_scal applies the same to occupied vs empty. We use l(x) =
-log(x), MonoScene's form: SurroundOcc's and Co3SOP's BCE(x, 1) is the same
function with the log clamped, so -log keeps it exact and says what it is.
Scales weigh 0.25 / 0.5 / 1 (1/4, 1/2, full resolution); the confidence loss
is the MSE between a voxel's confidence and the predicted probability of its
ground-truth class at the feature resolution.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from co3sop_nodes.common.classes import EMPTY, IGNORE

SCALE_WEIGHTS = (0.25, 0.5, 1.0)
SCALE_NAMES = ("1/4", "1/2", "1")
_EPS = 1e-6


def _log_terms(precision, recall, specificity) -> torch.Tensor:
    return -(precision.clamp(min=_EPS).log() + recall.clamp(min=_EPS).log() + specificity.clamp(min=_EPS).log())


def sem_scal(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """logits (B, K, ...), target (B, ...) with IGNORE -> scalar."""
    valid = target != IGNORE
    p = torch.softmax(logits, 1).movedim(1, -1)[valid]  # (N, K)
    y = target[valid]  # (N,)
    # every class at once, from per-class sums (a per-class column pick would zero-fill an (N, K) gradient each)
    k = p.shape[1]
    count = torch.bincount(y, minlength=k).to(p.dtype)  # (K,) voxels of class c
    present = count > 0
    if not present.any():
        return logits.sum() * 0
    hit = p.new_zeros(k).index_add(0, y, p.gather(1, y[:, None])[:, 0])  # sum of p_c over the voxels of class c
    mass = p.sum(0)  # sum of p_c over every voxel
    precision = hit / mass.clamp(min=_EPS)
    recall = hit / count.clamp(min=1)
    others = len(y) - count
    # sum of (1 - p_c) over the other voxels; a class that fills every valid voxel has no negatives: specificity 1
    specificity = torch.where(others > 0, (others - (mass - hit)) / others.clamp(min=1), torch.ones_like(hit))
    return _log_terms(precision[present], recall[present], specificity[present]).mean()


def geo_scal(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    valid = target != IGNORE
    p_empty = torch.softmax(logits, 1)[:, EMPTY][valid]  # (N,)
    q, t = 1 - p_empty, (target[valid] != EMPTY).float()
    precision = (q * t).sum() / q.sum().clamp(min=_EPS)
    recall = (q * t).sum() / t.sum().clamp(min=_EPS)
    specificity = ((1 - t) * p_empty).sum() / (1 - t).sum().clamp(min=_EPS)
    return _log_terms(precision, recall, specificity)


def downsample_labels(labels: torch.Tensor, factor: int, classes: int) -> torch.Tensor:
    """(B, X, Y, Z) labels -> (B, X/f, Y/f, Z/f) coarse targets.

    A block is its most frequent occupied label if it holds any (thin road lines
    and poles must survive the coarse scales), else empty, else ignore.
    """
    if factor == 1:
        return labels
    b, x, y, z = labels.shape
    blocks = labels.view(b, x // factor, factor, y // factor, factor, z // factor, factor).permute(0, 1, 3, 5, 2, 4, 6)
    blocks = blocks.reshape(b, x // factor, y // factor, z // factor, -1)
    # Per-block label histogram by one bincount (a one-hot of the full grid costs 25x its memory and time).
    coarse = blocks.shape[:-1]
    block_id = torch.arange(coarse.numel(), device=labels.device).view(*coarse, 1)
    keys = block_id * (classes + 1) + blocks.clamp(max=classes).long()  # ignore -> the extra, dropped column
    counts = torch.bincount(keys.flatten(), minlength=coarse.numel() * (classes + 1)).view(*coarse, classes + 1)[
        ..., :classes
    ]
    occupied = counts[..., EMPTY + 1 :]
    label = torch.where(occupied.sum(-1) > 0, occupied.argmax(-1) + EMPTY + 1, torch.full_like(counts[..., 0], EMPTY))
    return torch.where(counts.sum(-1) > 0, label, torch.full_like(label, IGNORE))


def occupancy_loss(logits: list[torch.Tensor], targets: list[torch.Tensor]) -> dict[str, torch.Tensor]:
    """Per scale: CE + sem_scal + geo_scal, weighted 0.25 / 0.5 / 1."""
    parts = {}
    for w, name, lg, tg in zip(SCALE_WEIGHTS, SCALE_NAMES, logits, targets):
        if not (tg != IGNORE).any():  # nothing to learn from at this scale
            parts[f"ce@{name}"] = parts[f"sem@{name}"] = parts[f"geo@{name}"] = lg.sum() * 0
            continue
        parts[f"ce@{name}"] = w * F.cross_entropy(lg, tg, ignore_index=IGNORE)
        parts[f"sem@{name}"] = w * sem_scal(lg, tg)
        parts[f"geo@{name}"] = w * geo_scal(lg, tg)
    return parts


def confidence_loss(confidence: torch.Tensor, logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """MSE between confidence (B, 1, X, Y, Z) and the predicted probability of the true class, on valid voxels."""
    valid = target != IGNORE
    prob = torch.softmax(logits, 1).gather(1, target.clamp(max=logits.shape[1] - 1)[:, None])[:, 0]
    return F.mse_loss(confidence[:, 0][valid], prob.detach()[valid]) if valid.any() else confidence.sum() * 0
