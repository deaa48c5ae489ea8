"""A dataset whose agents are held in memory (unit tests of what reads samples, without files)."""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from co3sop_nodes.train.dataset import AgentRecord, FrameIndex, OccupancyDataset


class MemoryDataset(OccupancyDataset):
    """frames: [((split, scenario, timestamp), [AgentRecord, ...]), ...], read as OccupancyDataset reads disk."""

    def __init__(self, frames: list[tuple[tuple[str, str, int], list[AgentRecord]]], cfg=None):
        self.cfg, self.keep, self._recent, self.cache = cfg, 0, OrderedDict(), None
        self.records = [agents for _, agents in frames]
        self.frames = [
            FrameIndex(key, tuple(str(a.cav_id) for a in agents), np.stack([a.world_from_lidar for a in agents]))
            for key, agents in frames
        ]
        self.scenarios = list(dict.fromkeys(frame.key[:2] for frame in self.frames))
        self.index = [(f, j) for f, frame in enumerate(self.frames) for j in range(len(frame.cavs))]

    def _read(self, f: int, j: int) -> AgentRecord:
        return self.records[f][j]
