"""What model tests share (unit and integration): a micro configuration, a small LiDAR model and scans for its int8
path, the head's paths against their dense reference."""

from __future__ import annotations

import numpy as np
import torch

from co3sop_nodes.inference.outputs import labels_from_logits
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import AttentionConfig, BackboneConfig, preset
from co3sop_nodes.model.head import OccupancyHead

# a model small enough to train for a few steps or time a frame in seconds on CPU, of any preset's structure
MICRO = dict(
    custom_grid=((-12.8, -12.8, -2.4), 0.4, (64, 64, 12)),
    image_size=(64, 48),
    backbone=BackboneConfig((1, 1, 1, 1), (8, 8, 16, 16), stem=8),
    fpn_channels=16,
    embed_dims=16,
    image_attention=AttentionConfig(1, 2, 2),
    fusion_attention=AttentionConfig(1, 2, 2),
    head_channels=(16, 8, 8),
)


LIDAR_GRID = ((-12.8, -12.8, -3.0), 0.4, (64, 64, 24))


def int8_pair_sums_saturate() -> bool:
    """Whether oneDNN's int8 convolution on this CPU sums pairs of uint8 x int8 products in 16 bits before 32,
    saturating (no VNNI: vpmaddubsw on AVX2): probed with 64 products of 255 x 127, whose pairs overflow 16 bits."""
    x = torch.full((1, 64, 1, 1, 1), 255, dtype=torch.uint8).contiguous(memory_format=torch.channels_last_3d)
    w = torch.full((1, 64, 1, 1, 1), 127, dtype=torch.int8)
    one, zero, unit, none = torch.ones(1, dtype=torch.float64), torch.zeros(1, dtype=torch.long), [1] * 3, [0] * 3
    packed = torch.ops.onednn.qconv_prepack(w, one, 1.0, 0, unit, none, unit, 1, None)
    out = torch.ops.onednn.qconv_pointwise(
        x, 1.0, 0, packed, one, zero, None, unit, none, unit, 1, 1.0, 0, torch.float32, "none", [], ""
    )
    return float(out.flatten()[0]) != 64 * 255 * 127


def scans(count: int, seed: int, dims=LIDAR_GRID[2]) -> list[torch.Tensor]:
    """Random occupancy scans (1, 1, X, Y, Z) uint8, 8 % of voxels hit."""
    gen = torch.Generator().manual_seed(seed)
    return [(torch.rand(1, 1, *dims, generator=gen) < 0.08).to(torch.uint8) for _ in range(count)]


def lidar_model(seed: int = 0):
    """A `tiny-lidar` of LIDAR_GRID with random weights, its encoder's norms not the identity."""
    torch.manual_seed(seed)
    model = build_model(preset("tiny-lidar", custom_grid=LIDAR_GRID)).eval()
    enc = model.vehicle.encoder
    for layer in (*enc.down, *enc.dilated):  # norms that are not the identity
        layer[1].running_mean.normal_(0, 0.1)
        layer[1].running_var.uniform_(0.5, 2.0)
    return model


def assert_labels_equal(labels: np.ndarray, want: np.ndarray, head: OccupancyHead, x: torch.Tensor) -> None:
    """Equal, but where float32 cannot rank the two best classes: any other summation order (threads, FMA, chunks)
    may flip a voxel whose two best logits differ by less than float32 rounding, in one voxel of ~10^6 here."""
    bad = np.flatnonzero(labels != want)
    if len(bad) == 0:
        return
    assert len(bad) <= max(1, want.size // 100_000), f"{len(bad)} of {want.size} labels differ"
    flat = torch.from_numpy(bad // want[0].size), torch.from_numpy(bad % want[0].size)
    with torch.no_grad():  # the exact logits of the differing voxels, in float64
        logits = torch.stack(
            [head.double().forward_at(x[i : i + 1].double(), v.reshape(1, 1))[-1][0, :, 0] for i, v in zip(*flat)]
        )
    head.float()
    top2 = logits.topk(2, dim=1).values  # (N, 2)
    assert ((top2[:, 0] - top2[:, 1]) <= 1e-5 * top2[:, 0].abs().clamp(min=1)).all(), (
        f"labels differ at {bad} beyond a float32 tie"
    )


def reference(head: OccupancyHead, x: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Labels and confidence from the dense logits (the definition), per batch item."""
    with torch.no_grad():
        logits = head(x)[-1]
    pairs = [labels_from_logits(logits[i : i + 1]) for i in range(len(x))]
    return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])
