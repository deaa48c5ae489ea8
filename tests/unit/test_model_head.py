"""The head's exact inference path (OccupancyHead.labels) against its reference, the dense pass + labels_from_logits."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from co3sop_nodes.model.config import preset
from co3sop_nodes.model.head import OccupancyHead
from co3sop_nodes.model.outputs import labels_from_logits


def random_head(channels: tuple[int, int, int], dims: int, seed: int) -> OccupancyHead:
    """A head with random weights large enough that many classes win somewhere, batch norm calibrated on noise."""
    torch.manual_seed(seed)
    head = OccupancyHead(dims, channels, 24)
    with torch.no_grad():
        for p in head.parameters():
            p.normal_(0, 0.3)
        head.train()(torch.randn(2, dims, 8, 8, 4))
    return head.eval()


def reference(head: OccupancyHead, x: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    with torch.no_grad():
        logits = head(x)[-1]
    pairs = [labels_from_logits(logits[i : i + 1]) for i in range(len(x))]
    return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])


@pytest.mark.parametrize("name, range_name", [("tiny", "25.6m"), ("tiny", "51.2m"), ("tiny", "76.8m"), ("tiny-lidar", "51.2m"),
                                              ("paper", "76.8m")])
def test_fast_labels_equal_the_dense_reference_at_every_range(name, range_name):
    cfg = preset(name, range=range_name)
    head = random_head(cfg.head_channels, cfg.embed_dims, 1)
    x = torch.randn(1, cfg.embed_dims, *cfg.feature_grid.dims)  # (B, C, X/4, Y/4, Z/4)
    want_labels, want_conf = reference(head, x)
    labels, conf = head.labels(x)
    assert labels.shape == conf.shape == (1, *cfg.grid.dims) and labels.dtype == conf.dtype == torch.uint8
    assert len(np.unique(want_labels)) >= 5  # a real test: many classes win somewhere
    np.testing.assert_array_equal(labels.numpy(), want_labels)
    assert np.abs(conf.numpy().astype(int) - want_conf).max() <= 1  # one step of 1/255 (float summation order)


@pytest.mark.parametrize("chunk", [1, 7, 100_000])
def test_chunking_and_batches_do_not_change_the_result(chunk):
    head = random_head((8, 8, 4), 8, 2)
    x = torch.randn(2, 8, 4, 6, 2)
    want_labels, want_conf = reference(head, x)
    labels, conf = head.labels(x, chunk=chunk)
    np.testing.assert_array_equal(labels.numpy(), want_labels)
    assert np.abs(conf.numpy().astype(int) - want_conf).max() <= 1
