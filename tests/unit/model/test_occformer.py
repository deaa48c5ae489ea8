"""OccFormer (model/occformer.py, mask_loss.py, matching.py): shapes, gradients, windows, matching, overfitting,
the fast labels against the dense definition, checkpoints."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from model_checks import MICRO

from co3sop_nodes.inference import pace
from co3sop_nodes.inference.checkpoint import export_model, load_model
from co3sop_nodes.inference.outputs import labels_from_logits
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import OccFormerConfig, preset
from co3sop_nodes.model.losses import confidence_loss, downsample_labels
from co3sop_nodes.model.mask_loss import class_guided_points, mask_classification_loss
from co3sop_nodes.model.matching import min_cost_assignment
from co3sop_nodes.model.occformer import OccFormerHead, WindowBlock, class_scores, log_scores, masks_at

OCC = OccFormerConfig(stages=(16, 32), blocks=2, window=7, queries=8, dims=16, layers=3, heads=2, points=2048)
CFG = preset("tiny-occformer", **MICRO, occformer=OCC)  # features 16 x 16 x 3, labels 64 x 64 x 12


def _labels(seed: int = 0) -> torch.Tensor:
    """(1, X, Y, Z) labels: ground, a few boxes of other classes, empty above, an ignored corner."""
    g = torch.Generator().manual_seed(seed)
    labels = torch.zeros(1, *CFG.grid.dims, dtype=torch.long)
    labels[..., :2] = 7
    for c in (1, 4, 10, 14):
        x, y = torch.randint(0, 48, (2,), generator=g).tolist()
        labels[:, x : x + 16, y : y + 16, 2:8] = c
    labels[:, :4, :4] = 255
    return labels


def test_predictions_have_the_decoder_shapes():
    torch.manual_seed(0)
    model = build_model(CFG).eval()
    ego = model.vehicle(**pace.shaped_inputs(model))
    with torch.no_grad():
        preds = model.ego(ego)
        coarse, fine = model.ego.head(ego.features)
    assert len(preds) == OCC.layers + 1
    for logits, masks in preds:
        assert logits.shape == (1, OCC.queries, CFG.num_classes + 1)
        assert masks.shape == (1, OCC.queries, *CFG.feature_grid.dims)
    assert coarse.shape == (1, CFG.num_classes, *CFG.feature_grid.dims) and fine.shape == (
        1,
        CFG.num_classes,
        *CFG.grid.dims,
    )


def test_every_parameter_gets_a_gradient():
    torch.manual_seed(1)
    model = build_model(CFG).train()
    ego = model.vehicle(**pace.shaped_inputs(model))
    preds = model.ego(ego)
    labels = _labels()
    parts = mask_classification_loss(preds, labels, OCC.points, np.random.default_rng(0))
    parts["confidence"] = confidence_loss(
        ego.confidence, log_scores(class_scores(*preds[-1])), downsample_labels(labels, 4, CFG.num_classes)
    )
    sum(parts.values()).backward()
    # the OccFormer side and the confidence it supervises (the camera lifting's own test is in test_model_halves)
    mine = [(n, p) for n, p in model.named_parameters() if n.startswith(("ego.", "vehicle.confidence"))]
    assert [n for n, p in mine if p.grad is None or not torch.any(p.grad != 0)] == []
    assert all(torch.isfinite(p.grad).all() for _, p in mine)


@pytest.mark.parametrize("shift", [False, True])
def test_a_window_block_mixes_only_within_its_window(shift):
    """A token's output depends on exactly the tokens of its window (after the cyclic shift, only those of its own
    side of the wrap-around), found from the input gradient."""
    torch.manual_seed(2)
    w, s, n = 5, 2, 10
    block = WindowBlock(8, 2, w, shift).eval()
    x = torch.randn(1, 8, n, n, requires_grad=True)
    for r, c in [(0, 0), (4, 7), (9, 9), (7, 2)]:
        (grad,) = torch.autograd.grad(block(x)[0, :, r, c].sum(), x)
        got = set(map(tuple, torch.nonzero(grad[0].abs().sum(0)).tolist()))

        def where(i):  # window and side of the wrap-around of row/column i, in the shifted frame
            k = (i - s) % n if shift else i
            return k // w, shift and k >= n - s

        want = {(i, j) for i in range(n) for j in range(n) if where(i) == where(r) and where(j) == where(c)}
        assert got == want, (r, c)


def test_masks_at_are_the_trilinear_upsampling():
    torch.manual_seed(3)
    masks = torch.randn(2, 3, 4, 5, 3)
    dims = (16, 20, 12)
    dense = F.interpolate(masks, size=dims, mode="trilinear", align_corners=True).flatten(2)  # (B, Q, N)
    index = torch.randint(0, 16 * 20 * 12, (2, 300))
    torch.testing.assert_close(
        masks_at(masks, index, dims), torch.gather(dense, 2, index[:, None].expand(-1, 3, -1)), atol=1e-5, rtol=1e-5
    )


def test_fast_labels_equal_the_dense_definition(monkeypatch):
    """The chunked labels against the dense log-scores, on decoder outputs where many classes win somewhere."""
    torch.manual_seed(4)
    head = OccFormerHead(CFG).eval()
    x = torch.randn(2, CFG.embed_dims, *CFG.feature_grid.dims)
    logits = torch.randn(2, OCC.queries, CFG.num_classes + 1) * 3  # (B, Q, K+1)
    masks = torch.randn(2, OCC.queries, *CFG.feature_grid.dims) * 4  # (B, Q, X/4, Y/4, Z/4)
    monkeypatch.setattr(head, "predict", lambda _: [(logits, masks)])
    labels, confidence = head.labels(x, chunk=5000)
    with torch.no_grad():
        fine = head(x)[-1]
    for i in range(2):
        want_labels, want_conf = labels_from_logits(fine[i : i + 1])
        assert (labels[i].numpy() != want_labels).mean() < 1e-4  # float32 ties only
        assert np.abs(confidence[i].numpy().astype(int) - want_conf).max() <= 1
        assert len(np.unique(want_labels)) >= 4


def test_min_cost_assignment_is_optimal():
    rng = np.random.default_rng(5)
    for trial in range(200):
        r, c = (int(v) for v in rng.integers(1, 6, 2))
        cost = rng.normal(size=(r, c)) if trial % 2 else rng.integers(0, 3, (r, c)).astype(float)  # ties too
        rows, cols = min_cost_assignment(cost)
        assert len(rows) == min(r, c) and len(set(rows)) == len(set(cols)) == min(r, c) and list(rows) == sorted(rows)
        if r <= c:
            best = min(sum(cost[i, p[i]] for i in range(r)) for p in itertools.permutations(range(c), r))
        else:
            best = min(sum(cost[p[j], j] for j in range(c)) for p in itertools.permutations(range(r), c))
        assert cost[rows, cols].sum() == pytest.approx(best)


def test_class_guided_points_favour_rare_classes_and_skip_ignored_voxels():
    labels = _labels()[0]
    index = class_guided_points(labels, 4000, np.random.default_rng(6))
    assert len(set(index.tolist())) == len(index) == 4000
    picked = labels.flatten()[index]
    assert (picked != 255).all()
    share = lambda t, c: float((t == c).float().mean())
    valid = labels[labels != 255]
    assert share(picked, 10) > 1.5 * share(valid, 10)  # a box of class 10 against mostly empty space
    assert share(picked, 0) < share(valid, 0)


def test_the_head_overfits_one_scene():
    """Trained on one feature volume and its labels, the decoder's masks and classes reproduce them."""
    torch.manual_seed(7)
    head = OccFormerHead(CFG)
    x = torch.randn(1, CFG.embed_dims, *CFG.feature_grid.dims)
    labels = _labels(1)
    opt = torch.optim.AdamW(head.parameters(), lr=2e-3)
    rng = np.random.default_rng(7)
    for _ in range(150):
        opt.zero_grad()
        sum(mask_classification_loss(head.predict(x), labels, OCC.points, rng).values()).backward()
        opt.step()
    predicted, _ = head.eval().labels(x)
    valid = labels != 255
    assert float((predicted.long() == labels)[valid].float().mean()) > 0.9


def test_an_occformer_checkpoint_round_trips(tmp_path):
    torch.manual_seed(8)
    model = build_model(CFG).eval()
    export_model(tmp_path / "m.pt", model, {"history": []}, half=False)
    loaded, _ = load_model(tmp_path / "m.pt")
    assert loaded.cfg == model.cfg and loaded.cfg.occformer == OCC
    inputs = pace.shaped_inputs(model)
    with torch.no_grad():
        a, b = (
            model.ego.head.labels(model.vehicle(**inputs).features),
            loaded.ego.head.labels(loaded.vehicle(**inputs).features),
        )
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_the_paper_size_preset_follows_occformer():
    cfg = preset("occformer")
    assert cfg.head == "occformer" and not cfg.fusion and cfg.modality == "camera"
    assert (cfg.occformer.queries, cfg.occformer.layers, cfg.occformer.dims, cfg.occformer.heads) == (100, 9, 192, 6)
    assert cfg.occformer.stages == (128, 256, 512, 1024) and cfg.occformer.blocks == 2 and cfg.occformer.window == 7
