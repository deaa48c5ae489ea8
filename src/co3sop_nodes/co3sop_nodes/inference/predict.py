"""One ego frame from what the ego holds: collaborators chosen, aligned, fused, labelled (ROS-free).

The ego node and offline bag evaluation both call `predict_frame`, so the
graph and the offline path make identical predictions from identical inputs.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from co3sop_nodes.inference.outputs import labels_from_logits
from co3sop_nodes.kernels import deform as deform_kernel
from co3sop_nodes.kernels import half_float, lidar_output, point_occupancy, quantized_add, visible_voxels
from co3sop_nodes.kernels import layer_norm as layer_norm_kernel
from co3sop_nodes.kernels import occupancy_conv as occupancy_kernel
from co3sop_nodes.kernels import octant as octant_kernel
from co3sop_nodes.kernels import quantize_volume as quantize_kernel
from co3sop_nodes.kernels import transpose as transpose_kernel
from co3sop_nodes.kernels.warp import compiled_available
from co3sop_nodes.model.co3sop import Co3SOP, VehicleOutput
from co3sop_nodes.v2x.neighbours import COMM_RANGE, nearest_collaborators, noisy_relative


@dataclass
class FramePrediction:
    labels: np.ndarray  # (X, Y, Z) uint8
    confidence: np.ndarray  # (X, Y, Z) uint8, round(255 * p(label))
    collaborators: list[int]  # used, nearest first
    fuse_s: float  # warp + fusion
    head_s: float


@torch.no_grad()
def predict_frame(
    model: Co3SOP,
    ego: VehicleOutput,
    world_from_ego: np.ndarray,
    candidates: Mapping[int, tuple[VehicleOutput, np.ndarray]],
    comm_range: float = COMM_RANGE,
    max_collaborators: int | None = None,
    mu: float = 0.0,
    sigma: float = 0.0,
    rng: np.random.Generator | None = None,
) -> FramePrediction:
    """candidates: agent id -> (its output as received, its world_from_lidar); all go to the model's device.

    On the model's inference path (`Co3SOP.use`); on its reference path (compiled kernels off), labels come
    from the head's dense logits (their definition) instead of its exact fast path.
    """
    k = model.cfg.max_collaborators if max_collaborators is None else max_collaborators
    chosen = nearest_collaborators(world_from_ego, {a: m for a, (_, m) in candidates.items()}, comm_range, k)
    rng = rng or np.random.default_rng(0)
    rel = [noisy_relative(world_from_ego, candidates[a][1], mu, sigma, rng) for a in chosen]
    device = model.path.torch_device
    ego = ego.to(device)
    t0 = time.perf_counter()
    fused = model.ego.fuse(
        ego,
        [candidates[a][0].to(device) for a in chosen],
        torch.from_numpy(np.stack(rel)).float()[None].to(device) if rel else None,
    )
    t1 = time.perf_counter()
    if not model.path.compiled:
        with model.path.autocast():
            labels, confidence = labels_from_logits(model.ego.head(fused)[-1].float())
    else:
        labels, confidence = (
            t[0].cpu().numpy() for t in model.ego.head.labels(fused)
        )  # exact fast path of labels_from_logits
    return FramePrediction(labels, confidence, chosen, t1 - t0, time.perf_counter() - t1)


def compile_kernels(model: Co3SOP, points: bool = False) -> list[str]:
    """Compile (or load from the cache) the CPU kernels `model`'s inputs (a LiDAR scan's binning), its inference and
    the feature codec use, and with `points` the point cloud's (an ego's picture of its prediction), so that no frame
    waits for a compiler: nodes call it before they say they are ready. The kernels that compiled, by name."""
    cfg = model.cfg
    _, c1, c2 = cfg.head_channels  # the last stage: 1/2 -> full resolution
    precision = model.path.floats
    kernels = (
        {"head": lambda: octant_kernel.available(c1, c2, cfg.num_classes, precision)} if cfg.head == "conv" else {}
    )
    if cfg.modality == "camera":
        kernels["image sampling"] = lambda: deform_kernel.available(cfg.embed_dims // cfg.image_attention.heads)
    else:
        kernels["scan binning"] = point_occupancy.available
    if cfg.modality == "lidar" and cfg.lidar.kind == "sscnet" and model.path.reduced:
        encoder = model.vehicle.encoder
        kernels["scan's first layer"] = lambda: occupancy_kernel.available(cfg.lidar.channels // 2, encoder.first_dtype)
        if model.path.int8:
            kernels["int8 residual sum"] = lambda: quantized_add.available(cfg.lidar.channels)
        if model.path.int8 and precision in lidar_output.FLOATS:
            kernels["scan's output layers"] = lambda: lidar_output.available(cfg.embed_dims, precision)
    if cfg.modality == "camera" or cfg.fusion:  # the transformer layers' sums and norms
        kernels["layer norm"] = lambda: layer_norm_kernel.available(cfg.embed_dims)
    if model.path.int8 and cfg.head == "conv":
        kernels["int8 head's input"] = lambda: quantize_kernel.available(cfg.embed_dims)
    if cfg.fusion:
        kernels["warp"] = compiled_available
        kernels["channels-last copies"] = transpose_kernel.available
        kernels["voxel sampling"] = lambda: deform_kernel.available(cfg.embed_dims // cfg.fusion_attention.heads)
    kernels["float16 codec"] = half_float.available  # every vehicle encodes, every ego decodes
    if points:
        kernels["point cloud"] = visible_voxels.available
    return [name for name, ready in kernels.items() if ready()]
