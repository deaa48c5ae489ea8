"""Offline predictions on a bag: the node graph's computation without DDS (ROS-free).

Reads the bag with rosbags, builds each CAV's inputs exactly as `vehicle`
does (same sensor_inputs, same mounts from /tf_static), passes every vehicle
output through the same feature codec and fuses with the same predict_frame
as `ego`. The graph's /ego/occupancy must equal these predictions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.data.bags import read_frames, read_static_transforms
from co3sop_nodes.inference.inputs import sensor_inputs, to_batch
from co3sop_nodes.inference.outputs import through_codec
from co3sop_nodes.inference.predict import FramePrediction, predict_frame
from co3sop_nodes.model.co3sop import Co3SOP, VehicleOutput
from co3sop_nodes.v2x.codec import FeatureCodecConfig


@torch.no_grad()
def vehicle_outputs(
    model: Co3SOP, bag: Path, cavs: list[int] | None = None
) -> dict[int, dict[int, tuple[VehicleOutput, np.ndarray]]]:
    """Stamp -> {cav: (its vehicle half's output, world_from_lidar)} for every frame of the bag, as `vehicle` computes
    them; `cavs` limits who takes part."""
    cfg = model.cfg
    mounts = read_static_transforms(bag)
    results = {}
    for stamp, agents in read_frames(bag):
        results[stamp] = {}
        for cav, data in sorted(agents.items()):
            if cavs is not None and cav not in cavs:
                continue
            if "pose" not in data:
                raise DatasetError(f"{bag}: frame {stamp} of cav {cav} has no pose")
            world_from_lidar = data["pose"]
            cameras = [
                (
                    name,
                    rgb,
                    data["intrinsics"][name],
                    mounts.lookup(topics.lidar_frame(cav), data["optical_frames"][name]),
                )
                for name, rgb in sorted(data["cameras"].items())
            ]
            inputs = sensor_inputs(cfg, world_from_lidar, cameras, data.get("points"))
            results[stamp][cav] = (model.vehicle(**to_batch(inputs)), world_from_lidar)
    return results


@torch.no_grad()
def predict_bag(
    model: Co3SOP, bag: Path, ego_id: int, codec: FeatureCodecConfig, cavs: list[int] | None = None, **predict_kw
) -> dict[int, FramePrediction]:
    """Stamp -> the ego's prediction, for every frame of the bag in which the ego appears; `cavs` limits who takes part."""
    results = {}
    for stamp, agents in vehicle_outputs(model, bag, cavs).items():
        if ego_id not in agents:
            continue
        received = {
            cav: (through_codec(model, out, codec)[0], world_from_lidar)
            for cav, (out, world_from_lidar) in agents.items()
        }
        ego, world_from_ego = received.pop(ego_id)
        results[stamp] = predict_frame(model, ego, world_from_ego, received, **predict_kw)
    return results
