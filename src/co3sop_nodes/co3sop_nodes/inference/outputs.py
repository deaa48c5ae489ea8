"""The model's outputs as they cross process boundaries (ROS-free), shared by offline evaluation and the nodes.

A vehicle half's output is encoded with a feature codec and decoded by the
ego exactly the same way in both paths, and the ego's logits become labels
the same way, so the graph and `evaluate` agree bit for bit.
"""

from __future__ import annotations

import numpy as np
import torch

from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.model.co3sop import VehicleOutput
from co3sop_nodes.v2x.codec import (
    DecodedFeatures,
    EncodedFeatures,
    FeatureCodecConfig,
    decode_features,
    encode_features,
)


def encode_output(
    out: VehicleOutput, grid: GridSpec, cfg: FeatureCodecConfig, request: np.ndarray | None = None
) -> EncodedFeatures:
    """A batch-of-one vehicle output -> what the vehicle sends (to the ego whose `request` it weighs, if any)."""
    return encode_features(out.features[0].cpu().numpy(), out.confidence[0, 0].cpu().numpy(), grid, cfg, request)


def decoded_output(dec: DecodedFeatures) -> VehicleOutput:
    """What the ego received -> a batch-of-one vehicle output (voxels not sent: features 0, confidence 0)."""
    conf = dec.confidence if dec.confidence is not None else np.zeros(dec.features.shape[1:], np.float32)
    return VehicleOutput(torch.from_numpy(dec.features)[None], torch.from_numpy(conf)[None, None])


def through_codec(
    out: VehicleOutput, grid: GridSpec, cfg: FeatureCodecConfig, request: np.ndarray | None = None
) -> tuple[VehicleOutput, int]:
    """A vehicle output as the ego receives it through `cfg` without DDS, and the bytes it took (payload and
    quantisation constants, as a byte budget counts them)."""
    enc = encode_output(out, grid, cfg, request)
    return decoded_output(decode_features(enc)), enc.budget_bytes


def labels_from_logits(logits: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution logits (1, K, X, Y, Z) -> labels (X, Y, Z) uint8 and round(255 * their probability) uint8.

    The reference of OccupancyHead.labels, which inference uses (tests hold them equal).
    """
    logits = logits.cpu()
    labels = logits[0].argmax(0)  # (X, Y, Z)
    prob = torch.softmax(logits[0], 0).gather(0, labels[None])[0]  # (X, Y, Z)
    return labels.numpy().astype(np.uint8), np.round(prob.numpy() * 255).astype(np.uint8)
