"""Unit tests for co3sop_nodes.model.losses against hand-computed values.

The small examples use logits = log(p) for chosen probability rows p (each
summing to 1), so the softmax is p exactly and every expected number below is
written out by hand from the MonoScene definitions quoted in losses.py.
"""

from __future__ import annotations

import math
from collections import Counter

import pytest
import torch

from co3sop_nodes.common.classes import EMPTY, IGNORE
from co3sop_nodes.model.losses import (
    SCALE_WEIGHTS,
    confidence_loss,
    downsample_labels,
    geo_scal,
    occupancy_loss,
    sem_scal,
)

# 4 voxels, 3 classes (0 = empty); the last voxel is ignored
PROBS = [
    [0.7, 0.2, 0.1],  # y = 0 (empty)
    [0.1, 0.6, 0.3],  # y = 1
    [0.2, 0.2, 0.6],  # y = 1
    [0.5, 0.25, 0.25],  # y = IGNORE
]
TARGET = [0, 1, 1, IGNORE]

# cross-entropy over the 3 valid voxels: -(ln p_y) averaged
CE = -(math.log(0.7) + math.log(0.6) + math.log(0.2)) / 3
# sem_scal, classes present: 0 and 1
#   class 0: p_0 = [.7, .1, .2], y==0 = [1, 0, 0]: P = .7 / 1.0, R = .7 / 1, S = (.9 + .8) / 2 = .85
#   class 1: p_1 = [.2, .6, .2], y==1 = [0, 1, 1]: P = .8 / 1.0, R = .8 / 2 = .4, S = .8 / 1
SEM = (-(math.log(0.7) + math.log(0.7) + math.log(0.85)) - (math.log(0.8) + math.log(0.4) + math.log(0.8))) / 2
# geo_scal: q = 1 - p_empty = [.3, .9, .8], occupied t = [0, 1, 1]:
#   P = 1.7 / 2.0 = .85, R = 1.7 / 2 = .85, S = (1 * .7) / 1 = .7
GEO = -(math.log(0.85) + math.log(0.85) + math.log(0.7))


def _example(shape=(1, 3, 4, 1, 1)):
    """logits (B, K, X, Y, Z) with softmax PROBS along X; target (B, X, Y, Z)."""
    logits = torch.tensor(PROBS, dtype=torch.float64).log().T.reshape(shape).contiguous()
    target = torch.tensor(TARGET).view(1, 4, 1, 1)
    return logits, target


def test_softmax_of_example_is_the_chosen_probabilities():
    logits, _ = _example()
    torch.testing.assert_close(torch.softmax(logits, 1)[0, :, :, 0, 0].T, torch.tensor(PROBS, dtype=torch.float64))


def test_sem_scal_hand_value():
    logits, target = _example()
    assert sem_scal(logits, target).item() == pytest.approx(SEM, rel=1e-6)


def test_geo_scal_hand_value():
    logits, target = _example()
    assert geo_scal(logits, target).item() == pytest.approx(GEO, rel=1e-6)


def test_cross_entropy_hand_value_in_occupancy_loss():
    logits, target = _example()
    parts = occupancy_loss([logits], [target])  # a single scale: weight 0.25
    assert set(parts) == {"ce@1/4", "sem@1/4", "geo@1/4"}
    assert parts["ce@1/4"].item() == pytest.approx(0.25 * CE, rel=1e-6)
    assert parts["sem@1/4"].item() == pytest.approx(0.25 * SEM, rel=1e-6)
    assert parts["geo@1/4"].item() == pytest.approx(0.25 * GEO, rel=1e-6)


def test_ignored_voxels_excluded():
    logits, target = _example()
    changed = logits.clone()
    changed[0, :, 3] = torch.tensor([5.0, -3.0, 9.0])[:, None, None]  # only the ignored voxel changes
    assert sem_scal(changed, target).item() == pytest.approx(SEM, rel=1e-6)
    assert geo_scal(changed, target).item() == pytest.approx(GEO, rel=1e-6)
    parts = occupancy_loss([changed], [target])
    assert parts["ce@1/4"].item() == pytest.approx(0.25 * CE, rel=1e-6)
    # ... whereas changing a valid voxel does change them
    changed[0, :, 1] = torch.tensor([5.0, -3.0, 9.0])[:, None, None]
    assert sem_scal(changed, target).item() != pytest.approx(SEM, rel=1e-3)
    assert geo_scal(changed, target).item() != pytest.approx(GEO, rel=1e-3)


def test_all_ignored_gives_zero_losses_with_gradient():
    logits = torch.randn(1, 3, 2, 1, 1, requires_grad=True)
    target = torch.full((1, 2, 1, 1), IGNORE)
    s = sem_scal(logits, target)
    assert s.item() == 0.0
    s.backward()
    assert logits.grad is not None


def test_sem_scal_perfect_prediction_is_near_zero_and_wrong_prediction_large():
    target = torch.tensor([0, 1, 2, 2]).view(1, 4, 1, 1)
    good = torch.nn.functional.one_hot(target, 3).permute(0, 4, 1, 2, 3).double() * 30
    bad = torch.nn.functional.one_hot((target + 1) % 3, 3).permute(0, 4, 1, 2, 3).double() * 30
    assert sem_scal(good, target).item() < 1e-6
    assert geo_scal(good, target).item() < 1e-6
    assert sem_scal(bad, target).item() > 5


def test_sem_scal_single_class_specificity_is_one():
    """Only one class present and every voxel that class: specificity has no negatives and counts as 1."""
    probs = torch.tensor([[0.2, 0.8], [0.4, 0.6]], dtype=torch.float64)
    logits = probs.log().T.reshape(1, 2, 2, 1, 1)
    target = torch.tensor([1, 1]).view(1, 2, 1, 1)
    # class 1: P = 1.4 / 1.4 = 1, R = 1.4 / 2 = .7, S := 1
    assert sem_scal(logits, target).item() == pytest.approx(-math.log(0.7), rel=1e-6)


def test_occupancy_loss_scale_weights():
    torch.manual_seed(0)
    logits = [torch.randn(1, 5, 2, 2, 2), torch.randn(1, 5, 4, 4, 4), torch.randn(1, 5, 8, 8, 8)]
    targets = [torch.randint(0, 5, (1, n, n, n)) for n in (2, 4, 8)]
    targets[2][0, 0] = IGNORE
    parts = occupancy_loss(logits, targets)
    assert SCALE_WEIGHTS == (0.25, 0.5, 1.0)
    assert set(parts) == {f"{k}@{n}" for k in ("ce", "sem", "geo") for n in ("1/4", "1/2", "1")}
    for w, n, lg, tg in zip((0.25, 0.5, 1.0), ("1/4", "1/2", "1"), logits, targets):
        ce = torch.nn.functional.cross_entropy(lg, tg, ignore_index=IGNORE)
        assert parts[f"ce@{n}"].item() == pytest.approx(w * ce.item(), rel=1e-5)
        assert parts[f"sem@{n}"].item() == pytest.approx(w * sem_scal(lg, tg).item(), rel=1e-5)
        assert parts[f"geo@{n}"].item() == pytest.approx(w * geo_scal(lg, tg).item(), rel=1e-5)


def test_occupancy_loss_hand_values_per_scale():
    logits, target = _example()
    small = logits[:, :, :2].contiguous(), target[:, :2].contiguous()  # voxels 0, 1: X = 2
    parts = occupancy_loss([small[0], logits, logits], [small[1], target, target])
    assert parts["ce@1/4"].item() == pytest.approx(0.25 * -(math.log(0.7) + math.log(0.6)) / 2, rel=1e-6)
    for w, name in ((0.5, "1/2"), (1.0, "1")):
        assert parts[f"ce@{name}"].item() == pytest.approx(w * CE, rel=1e-6)
        assert parts[f"sem@{name}"].item() == pytest.approx(w * SEM, rel=1e-6)
        assert parts[f"geo@{name}"].item() == pytest.approx(w * GEO, rel=1e-6)


# ---------------------------------------------------------------- downsample_labels


def test_downsample_labels_block_rules():
    k = 10
    labels = torch.zeros(1, 4, 4, 2, dtype=torch.long)  # factor 2 -> (2, 2, 1): four 2x2x2 blocks
    blk = {
        (0, 0): (slice(0, 2), slice(0, 2)),
        (0, 1): (slice(0, 2), slice(2, 4)),
        (1, 0): (slice(2, 4), slice(0, 2)),
        (1, 1): (slice(2, 4), slice(2, 4)),
    }
    # block (0, 0): 7 empty + one pole voxel (9): any occupied voxel wins over empty
    labels[0, 1, 0, 1] = 9
    # block (0, 1): occupied 3, 3, 5 among empty: the most frequent occupied label (3), not empty
    labels[0, 0, 2, 0] = 3
    labels[0, 1, 3, 1] = 3
    labels[0, 0, 3, 1] = 5
    # block (1, 0): all ignored
    xs, ys = blk[(1, 0)]
    labels[0, xs, ys, :] = IGNORE
    # block (1, 1): all empty
    out = downsample_labels(labels, 2, k)
    assert out.shape == (1, 2, 2, 1)
    assert out[0, :, :, 0].tolist() == [[9, 3], [IGNORE, EMPTY]]


def test_downsample_labels_ignore_mixed_blocks():
    labels = torch.full((1, 2, 2, 4), IGNORE, dtype=torch.long)  # factor 2 -> two blocks along z
    labels[0, 0, 0, 0] = EMPTY  # block 0: ignore + empty -> empty
    labels[0, 1, 1, 3] = 4  # block 1: ignore + one occupied -> occupied
    out = downsample_labels(labels, 2, 6)
    assert out[0, 0, 0].tolist() == [EMPTY, 4]


def test_downsample_labels_factor_one_is_identity():
    labels = torch.randint(0, 5, (1, 2, 3, 4))
    assert torch.equal(downsample_labels(labels, 1, 5), labels)


@pytest.mark.parametrize("factor", [2, 4])
def test_downsample_labels_matches_counting_reference(factor):
    torch.manual_seed(factor)
    k = 6
    b, n = 2, 8
    # mostly empty with sparse classes and ignores; avoid ties between occupied labels by weighting
    labels = torch.multinomial(torch.tensor([6.0, 1, 1, 1, 1, 1, 2]), b * n * n * n, replacement=True).view(b, n, n, n)
    labels[labels == 6] = IGNORE
    labels[0, :factor, :factor, :factor] = IGNORE  # one all-ignored block
    labels[1, :factor, :factor, :factor] = EMPTY  # one all-empty block
    out = downsample_labels(labels, factor, k)
    m = n // factor
    assert out.shape == (b, m, m, m)
    checked = 0
    for bi in range(b):
        for i in range(m):
            for j in range(m):
                for kk in range(m):
                    block = labels[
                        bi,
                        i * factor : (i + 1) * factor,
                        j * factor : (j + 1) * factor,
                        kk * factor : (kk + 1) * factor,
                    ]
                    counts = Counter(block.flatten().tolist())
                    occupied = {c: v for c, v in counts.items() if c not in (EMPTY, IGNORE)}
                    if occupied:
                        top = max(occupied.values())
                        winners = [c for c, v in occupied.items() if v == top]
                        if len(winners) > 1:
                            assert out[bi, i, j, kk].item() in winners
                            continue
                        expected = winners[0]
                    elif counts.get(EMPTY, 0):
                        expected = EMPTY
                    else:
                        expected = IGNORE
                    assert out[bi, i, j, kk].item() == expected, (bi, i, j, kk, counts)
                    checked += 1
    assert checked > m**3  # most blocks had a unique answer
    assert out[0, 0, 0, 0] == IGNORE and out[1, 0, 0, 0] == EMPTY


# ---------------------------------------------------------------- confidence_loss


def test_confidence_loss_is_mse_to_detached_true_class_probability():
    logits, target = _example()  # true-class probabilities .7, .6, .2 (voxel 3 ignored)
    logits = logits.float().requires_grad_(True)
    conf = torch.tensor([0.5, 0.9, 0.2, 0.0]).view(1, 1, 4, 1, 1).requires_grad_(True)
    loss = confidence_loss(conf, logits, target)
    expected = ((0.5 - 0.7) ** 2 + (0.9 - 0.6) ** 2 + (0.2 - 0.2) ** 2) / 3
    assert loss.item() == pytest.approx(expected, rel=1e-5)
    loss.backward()
    assert logits.grad is None or torch.count_nonzero(logits.grad) == 0  # the target probability is detached
    torch.testing.assert_close(
        conf.grad.view(4), torch.tensor([2 * (0.5 - 0.7), 2 * (0.9 - 0.6), 0.0, 0.0]) / 3, atol=1e-6, rtol=1e-5
    )


def test_confidence_loss_all_ignored_is_zero():
    conf = torch.rand(1, 1, 2, 1, 1, requires_grad=True)
    loss = confidence_loss(conf, torch.randn(1, 3, 2, 1, 1), torch.full((1, 2, 1, 1), IGNORE))
    assert loss.item() == 0.0
    loss.backward()
    assert conf.grad is not None


# ---------------------------------------------------------------- no valid voxel at all


def test_occupancy_loss_all_ignored_target_is_zero():
    logits = torch.randn(1, 3, 2, 2, 2, requires_grad=True)
    target = torch.full((1, 2, 2, 2), IGNORE)
    parts = occupancy_loss([logits], [target])
    assert parts["sem@1/4"].item() == 0.0  # the guarded term
    assert {k: v.item() for k, v in parts.items()} == {"ce@1/4": 0.0, "sem@1/4": 0.0, "geo@1/4": 0.0}


@pytest.mark.parametrize("seed", range(4))
def test_downsample_labels_equals_counting_every_block(seed):
    """The bincount histogram against the rule applied block by block (ties: the lowest occupied label)."""
    g = torch.Generator().manual_seed(seed)
    k, f = 6, 2
    labels = torch.randint(0, k, (2, 4, 6, 4), generator=g)
    labels[torch.rand(labels.shape, generator=g) < 0.3] = IGNORE
    labels[torch.rand(labels.shape, generator=g) < 0.3] = EMPTY
    out = downsample_labels(labels, f, k)
    for b, i, j, k in torch.cartesian_prod(*(torch.arange(n) for n in out.shape)).tolist():
        block = labels[b, i * f : (i + 1) * f, j * f : (j + 1) * f, k * f : (k + 1) * f].flatten().tolist()
        counts = Counter(v for v in block if v != IGNORE)
        occupied = {c: n for c, n in counts.items() if c != EMPTY}
        best = min(occupied, key=lambda c: (-occupied[c], c)) if occupied else (EMPTY if counts else IGNORE)
        assert out[b, i, j, k].item() == best, (b, i, j, k, block)


@pytest.mark.parametrize("seed", range(3))
def test_sem_scal_equals_the_definition_class_by_class(seed):
    """The vectorised sem_scal against MonoScene's definition written as a loop over the present classes."""
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(2, 5, 7, 3, generator=g)
    target = torch.randint(0, 5, (2, 7, 3), generator=g)
    target[torch.rand(target.shape, generator=g) < 0.2] = IGNORE
    valid = target != IGNORE
    p, y = torch.softmax(logits, 1).movedim(1, -1)[valid], target[valid]
    terms = []
    for c in torch.unique(y).tolist():
        pc, is_c = p[:, c], (y == c).float()
        precision, recall = (pc * is_c).sum() / pc.sum(), (pc * is_c).sum() / is_c.sum()
        specificity = ((1 - pc) * (1 - is_c)).sum() / (1 - is_c).sum()
        terms.append(-(precision.log() + recall.log() + specificity.log()))
    assert sem_scal(logits, target).item() == pytest.approx(torch.stack(terms).mean().item(), rel=1e-5)
