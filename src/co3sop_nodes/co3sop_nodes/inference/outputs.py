"""The model's outputs as they cross process boundaries (ROS-free), shared by offline evaluation and the nodes.

A vehicle half's output is encoded with a feature codec and decoded by the
ego exactly the same way in both paths, and the ego's logits become labels
the same way, so the graph and `evaluate` agree bit for bit.
"""

from __future__ import annotations

import numpy as np
import torch

from co3sop_nodes.common.errors import CodecError
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.model.co3sop import Co3SOP, VehicleOutput
from co3sop_nodes.v2x.codec import (
    DEFAULT_MAX_RAW_BYTES,
    DecodedFeatures,
    EncodedFeatures,
    FeatureCodecConfig,
    decode_features,
    encode_features,
)
from co3sop_nodes.v2x.scan import EncodedScan, ScanCodecConfig, decode_scan, encode_scan


def code_id(model: Co3SOP) -> str:
    """The name of the model's learned wire code ("" without one)."""
    return model.vehicle.wire.code_id() if model.vehicle.wire is not None else ""


def encode_output(
    out: VehicleOutput,
    grid: GridSpec,
    cfg: FeatureCodecConfig,
    request: np.ndarray | None = None,
    learned_code: str = "",
) -> EncodedFeatures:
    """A batch-of-one vehicle output -> what the vehicle sends (to the ego whose `request` it weighs, if any); with
    a learned codec, its wire code, named `learned_code` (code_id of the model)."""
    confidence = out.confidence[0, 0].cpu().numpy()
    if not cfg.learned:
        return encode_features(out.features[0].cpu().numpy(), confidence, grid, cfg, request)
    if out.code is None:
        raise CodecError("a learned codec needs a model with a learned wire code (trained with train --stage wire)")
    return encode_features(out.code[0].cpu().numpy(), confidence, grid, cfg, request, learned_code)


def decoded_output(dec: DecodedFeatures, model: Co3SOP | None = None) -> VehicleOutput:
    """What the ego received -> a batch-of-one vehicle output (voxels not sent: features 0, confidence 0); a
    learned code is decoded by `model`'s, which must be the code it was sent in."""
    if dec.learned_code:
        have = code_id(model) if model is not None else ""
        if dec.learned_code != have:
            raise CodecError(
                f"learned_code: {dec.learned_code!r}, but this model's code is "
                f"{have!r}" + ("" if have else " (none: it decodes no learned code)")
            )
        if dec.features.shape[0] != model.cfg.wire.rank:
            raise CodecError(f"channels: {dec.features.shape[0]}, but the code has {model.cfg.wire.rank} per voxel")
        with torch.no_grad():
            device = model.path.torch_device
            code, mask = torch.from_numpy(dec.features)[None].to(device), torch.from_numpy(dec.mask)[None].to(device)
            return model.ego.receive(code, mask)
    conf = dec.confidence if dec.confidence is not None else np.zeros(dec.features.shape[1:], np.float32)
    return VehicleOutput(torch.from_numpy(dec.features)[None], torch.from_numpy(conf)[None, None])


def through_codec(
    model: Co3SOP, out: VehicleOutput, cfg: FeatureCodecConfig, request: np.ndarray | None = None
) -> tuple[VehicleOutput, int]:
    """A vehicle output of `model` as its ego receives it through `cfg` without DDS, and the bytes it took (payload
    and quantisation constants, as a byte budget counts them)."""
    enc = encode_output(out, model.cfg.feature_grid, cfg, request, code_id(model) if cfg.learned else "")
    return decoded_output(decode_features(enc), model), enc.budget_bytes


def scan_output(enc: EncodedScan, model: Co3SOP, max_raw_bytes: int = DEFAULT_MAX_RAW_BYTES) -> VehicleOutput:
    """A neighbour's scan message -> its output as fusion takes it: `model`'s vehicle half run on the scan, as the
    sender's own would (a LiDAR model's vehicle half sees nothing else). Raises CodecError on a scan of another
    grid than the model's (voxel size and origin included) or a bad payload."""
    if model.cfg.modality != "lidar":
        raise CodecError(f"{model.cfg.name}: a {model.cfg.modality} model encodes no LiDAR scan")
    grid, have = enc.grid, model.cfg.grid
    if grid != have:
        raise CodecError(
            f"grid {'x'.join(map(str, grid.dims))} @ {grid.voxel_size:g} m does not match the model's "
            f"{'x'.join(map(str, have.dims))} @ {have.voxel_size:g} m"
        )
    occupancy = decode_scan(enc, max_raw_bytes)  # (X, Y, Z) bool
    with torch.no_grad():
        scan = torch.from_numpy(occupancy.astype(np.uint8))[None, None].to(model.path.torch_device)  # (1, 1, X, Y, Z)
        return model.vehicle(occupancy=scan)


def through_scan(model: Co3SOP, occupancy: np.ndarray, cfg: ScanCodecConfig) -> tuple[VehicleOutput, int]:
    """A neighbour's scan (1, X, Y, Z) as its ego receives it through `cfg` without DDS, encoded by the ego's
    `model`, and the bytes it took."""
    enc = encode_scan(occupancy[0], model.cfg.grid, cfg)
    return scan_output(enc, model), enc.budget_bytes


def labels_from_logits(logits: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution logits (1, K, X, Y, Z) -> labels (X, Y, Z) uint8 and round(255 * their probability) uint8.

    The reference of OccupancyHead.labels, which inference uses (tests hold them equal).
    """
    logits = logits.cpu()
    labels = logits[0].argmax(0)  # (X, Y, Z)
    prob = torch.softmax(logits[0], 0).gather(0, labels[None])[0]  # (X, Y, Z)
    return labels.numpy().astype(np.uint8), np.round(prob.numpy() * 255).astype(np.uint8)
