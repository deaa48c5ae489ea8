"""Input controls: the same samples with blank or shuffled sensor data, to catch a model that ignores its sensors.

- "real": the agent's own inputs.
- "blank": no sensor content: every image a uniform mid grey, or an empty
  LiDAR scan. A model that scores as well without its sensors predicts a prior.
- "shuffled": every agent's sensor data taken from another scenario (the
  next one in the dataset's order, same frame position and agent position,
  wrapping around): real-looking inputs of the wrong place.
Calibration (lidar2img) and poses stay the agent's own: only what the sensors
saw is replaced.
"""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.train.dataset import OccupancyDataset

INPUT_CONTROLS = ("real", "blank", "shuffled")
SENSOR_KEYS = ("images", "occupancy")  # VehicleHalf inputs that carry sensor content (camera / LiDAR)
GREY = 128


class ControlledInputs:
    """Inputs of agent j of frame f of a dataset under one of INPUT_CONTROLS."""

    def __init__(self, dataset: OccupancyDataset, mode: str):
        if mode not in INPUT_CONTROLS:
            raise ValueError(f"input control {mode!r} (known: {', '.join(INPUT_CONTROLS)})")
        self.dataset, self.mode = dataset, mode
        by_scenario: dict[tuple[str, str], list[int]] = {}
        for f, frame in enumerate(dataset.frames):
            by_scenario.setdefault(frame.key[:2], []).append(f)
        self.scenarios = list(by_scenario.values())  # frame indices per scenario, dataset order
        self.position = {f: (s, i) for s, frames in enumerate(self.scenarios) for i, f in enumerate(frames)}
        if mode == "shuffled" and len(self.scenarios) < 2:
            raise DatasetError("the shuffled input control needs at least two scenarios")

    def __call__(self, f: int, j: int) -> dict:
        inputs = self.dataset.agent(f, j).inputs
        if self.mode == "real":
            return inputs
        if self.mode == "blank":
            return {
                k: (np.full_like(v, GREY if k == "images" else 0) if k in SENSOR_KEYS else v) for k, v in inputs.items()
            }
        s, i = self.position[f]
        donors = self.scenarios[(s + 1) % len(self.scenarios)]
        d = donors[i % len(donors)]
        donor = self.dataset.agent(d, j % len(self.dataset.frames[d].cavs)).inputs
        return {k: (donor[k] if k in SENSOR_KEYS else v) for k, v in inputs.items()}
