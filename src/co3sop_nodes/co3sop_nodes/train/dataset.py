"""Samples for training and evaluation: every CAV of every frame is the ego in turn (as Co3SOP).

A sample is the ego's inputs and labels plus its collaborators (other CAVs of
the frame within the communication range, nearest first), each with its inputs
and the transform neighbour_from_ego between the two LiDAR frames. Frames are
read once from the OPV2V folder and kept in memory.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.data import opv2v
from co3sop_nodes.inference.inputs import camera_inputs, lidar_occupancy, merged_occupancy
from co3sop_nodes.model.config import ModelConfig
from co3sop_nodes.v2x.neighbours import nearest_collaborators


@dataclass
class AgentRecord:
    cav_id: int
    world_from_lidar: np.ndarray  # (4, 4)
    inputs: dict  # numpy VehicleHalf inputs (images + lidar2img, or occupancy)
    labels: np.ndarray | None  # (X, Y, Z) uint8 at the model's range


@dataclass
class Sample:
    key: tuple[str, str, int, int]  # split, scenario, timestamp, ego cav
    ego: AgentRecord
    others: list[AgentRecord]  # nearest first
    neighbour_from_ego: np.ndarray  # (A, 4, 4)


def early_fused(sample: Sample, grid: GridSpec, scan=lambda record: record.inputs["occupancy"]) -> Sample:
    """The sample as an early-fusion model sees it: the ego's scan merged with its collaborators' (`scan`: an
    agent's (1, X, Y, Z) occupancy, its own by default, or an input control's), and no collaborator left to fuse."""
    merged = merged_occupancy(scan(sample.ego), [scan(a) for a in sample.others], sample.neighbour_from_ego, grid)
    return replace(
        sample, ego=replace(sample.ego, inputs={"occupancy": merged}), others=[], neighbour_from_ego=np.zeros((0, 4, 4))
    )


class OccupancyDataset:
    def __init__(self, root: Path, splits: list[str], cfg: ModelConfig, max_scenarios: int | None = None):
        self.cfg = cfg
        self.frames: list[tuple[tuple[str, str, int], list[AgentRecord]]] = []
        scenarios = [(s, n) for s, n in opv2v.find_scenarios(root) if s in splits][:max_scenarios]
        if not scenarios:
            raise DatasetError(f"{root}: no scenarios in split(s) {', '.join(splits)}")
        for split, name in scenarios:
            for ts, frames in opv2v.read_scenario(root, split, name, (cfg.range,), points=cfg.modality == "lidar"):
                if isinstance(frames, DatasetError):
                    raise frames
                self.frames.append(((split, name, ts), [self._record(f) for f in frames]))
        self.scenarios = list(dict.fromkeys(key[:2] for key, _ in self.frames))  # (split, name) with frames, in order
        self.index = [(i, j) for i, (_, agents) in enumerate(self.frames) for j in range(len(agents))]

    def _record(self, frame) -> AgentRecord:
        if self.cfg.modality == "camera":
            images, lidar2img = camera_inputs(frame.cameras, frame.world_from_lidar, self.cfg.image_size)
            inputs = {"images": images, "lidar2img": lidar2img}
        else:
            inputs = {"occupancy": lidar_occupancy(frame.points, self.cfg.grid)}
        return AgentRecord(frame.cav_id, frame.world_from_lidar, inputs, frame.labels.get(self.cfg.range))

    def __len__(self) -> int:
        return len(self.index)

    def sample(self, i: int, max_collaborators: int | None = None) -> Sample:
        f, j = self.index[i]
        (split, name, ts), agents = self.frames[f]
        ego = agents[j]
        by_id = {a.cav_id: a for a in agents if a is not ego}
        k = self.cfg.max_collaborators if max_collaborators is None else max_collaborators
        others = [
            by_id[i]
            for i in nearest_collaborators(ego.world_from_lidar, {i: a.world_from_lidar for i, a in by_id.items()}, k=k)
        ]
        rel = (
            np.stack([np.linalg.inv(a.world_from_lidar) @ ego.world_from_lidar for a in others])
            if others
            else np.zeros((0, 4, 4))
        )
        return Sample((split, name, ts, ego.cav_id), ego, others, rel)
