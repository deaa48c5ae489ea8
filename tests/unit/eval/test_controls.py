"""Input controls: blank and shuffled sensors replace what the sensors saw and nothing else."""

import numpy as np
import pytest
from memory_dataset import MemoryDataset

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.eval.controls import GREY, ControlledInputs
from co3sop_nodes.train.dataset import AgentRecord


def fake_dataset(scenarios: int, frames: int = 2, agents: int = 2, modality: str = "camera") -> MemoryDataset:
    """A dataset whose every input is filled with a value naming its scenario, frame and agent."""
    stored = []
    for s in range(scenarios):
        for t in range(frames):
            records = []
            for j in range(agents):
                tag = 100 * s + 10 * t + j
                if modality == "camera":
                    inputs = {
                        "images": np.full((4, 3, 6, 8), tag, np.uint8),
                        "lidar2img": np.full((4, 4, 4), tag, np.float32),
                    }
                else:
                    inputs = {"occupancy": np.full((1, 4, 4, 2), tag % 2 + 1, np.uint8)}
                records.append(AgentRecord(j, np.eye(4), inputs, None))
            stored.append((("test", f"s{s}", t), records))
    return MemoryDataset(stored)


def test_real_inputs_are_the_agents_own():
    dataset = fake_dataset(2)
    assert ControlledInputs(dataset, "real")(3, 1) is dataset.records[3][1].inputs


def test_blank_inputs_keep_the_calibration():
    dataset = fake_dataset(2)
    got = ControlledInputs(dataset, "blank")(3, 1)
    assert (got["images"] == GREY).all() and got["images"].dtype == np.uint8
    np.testing.assert_array_equal(got["lidar2img"], dataset.records[3][1].inputs["lidar2img"])
    lidar = ControlledInputs(fake_dataset(2, modality="lidar"), "blank")(0, 0)
    assert not lidar["occupancy"].any() and lidar["occupancy"].shape == (1, 4, 4, 2)


def test_shuffled_inputs_come_from_the_next_scenario_at_the_same_positions():
    dataset = fake_dataset(3)
    control = ControlledInputs(dataset, "shuffled")
    for f in range(len(dataset.frames)):
        s, t = divmod(f, 2)
        for j in range(2):
            got = control(f, j)
            assert (got["images"] == 100 * ((s + 1) % 3) + 10 * t + j).all()  # another scenario's sensors ...
            assert (got["lidar2img"] == 100 * s + 10 * t + j).all()  # ... with the agent's own calibration


def test_shuffled_needs_two_scenarios_and_modes_are_checked():
    with pytest.raises(DatasetError, match="two scenarios"):
        ControlledInputs(fake_dataset(1), "shuffled")
    with pytest.raises(ValueError, match="noise"):
        ControlledInputs(fake_dataset(2), "noise")
