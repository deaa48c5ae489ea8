"""An early-fusion model in training and in learn.evaluate: its one network sees the ego's scan merged with its
collaborators' (in evaluation: none when off, under the input controls and the pose noise; nothing encoded)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from memory_dataset import MemoryDataset

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.eval.evaluate import evaluate
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import LidarConfig, preset
from co3sop_nodes.train.dataset import AgentRecord
from co3sop_nodes.train.trainer import _Forward, training_sample
from co3sop_nodes.v2x.codec import FeatureCodecConfig

GRID = GridSpec((-6.4, -6.4, -2.0), 0.4, (32, 32, 8))
CFG = preset(
    "tiny-sscnet-early",
    custom_grid=(GRID.origin, GRID.voxel_size, GRID.dims),
    lidar=LidarConfig("sscnet", 8),
    embed_dims=8,
    head_channels=(8, 8, 8),
)
OWN = {0: (10, 16, 4), 1: (11, 16, 4)}  # each agent's one occupied voxel in its own grid
MERGED = {0: {(10, 16, 4), (16, 16, 4)}, 1: {(11, 16, 4), (5, 16, 4)}}  # agent 1 is 2 m (5 voxels) ahead of agent 0


def dataset(scenarios: int = 2) -> MemoryDataset:
    """Two agents per frame, agent 1 2 m ahead of agent 0, one frame per scenario."""
    frames = []
    for s in range(scenarios):
        records = []
        for j in (0, 1):
            pose = np.eye(4)
            pose[0, 3] = 2.0 * j
            occupancy = np.zeros((1, *GRID.dims), np.uint8)
            occupancy[(0, *OWN[j])] = 1
            records.append(AgentRecord(j, pose, {"occupancy": occupancy}, np.zeros(GRID.dims, np.uint8)))
        frames.append((("test", f"s{s}", 0), records))
    return MemoryDataset(frames, CFG)


@pytest.fixture
def model_and_scans():
    torch.manual_seed(0)
    model = build_model(CFG).eval()
    scans, forward = [], model.vehicle.forward

    def recorded(**inputs):  # the scans the network is fed, in order
        scans.append({tuple(v) for v in np.argwhere(inputs["occupancy"][0, 0].numpy())})
        return forward(**inputs)

    model.vehicle.forward = recorded
    return model, scans


def test_off_feeds_the_ego_scan_and_on_the_merged_one(model_and_scans):
    model, scans = model_and_scans
    data, cache = dataset(), {}
    evaluate(model, data, collaborators=0, cache=cache)
    assert scans == [{OWN[0]}, {OWN[1]}] * 2
    scans.clear()
    evaluate(model, data, cache=cache)  # the scans merged with 1 collaborator: not the outputs kept for 0
    assert scans == [MERGED[0], MERGED[1]] * 2
    scans.clear()
    evaluate(model, data, collaborators=0, cache=cache)
    evaluate(model, data, cache=cache)
    assert scans == []  # both kept, each under its collaborators


def test_input_controls_apply_to_every_scan_before_the_merge(model_and_scans):
    model, scans = model_and_scans
    evaluate(model, dataset(), inputs="blank")
    assert scans == [set()] * 4


def test_pose_noise_moves_the_collaborators_scans_each_time(model_and_scans):
    model, scans = model_and_scans
    data, cache = dataset(1), {}
    evaluate(model, data, cache=cache)
    for seed in (1, 2):  # drawn anew (the network runs again) and never kept
        evaluate(model, data, mu=1.0, sigma=0.2, seed=seed, cache=cache)
    assert len(scans) == 6
    for scan in scans[2::2]:  # ego 0: its own voxel, and the neighbour's ~1 m (2.5 voxels) off along x and y
        ((x, y, z),) = scan - {OWN[0]}
        assert 17 <= x <= 20 and 17 <= y <= 20 and z == 4, scan
    scans.clear()
    evaluate(model, data, cache=cache)
    assert scans == []  # the noiseless merges kept from the first call, not overwritten by noisy ones


def test_no_features_to_encode():
    with pytest.raises(Co3sopError, match="early-fusion"):
        evaluate(build_model(CFG), dataset(), codec=FeatureCodecConfig())


def test_training_feeds_the_merged_scans_and_no_collaborator(model_and_scans):
    model, scans = model_and_scans
    forward, data = _Forward(model.train(), "ego", torch.device("cpu")), dataset(1)
    index = torch.arange(0, GRID.dims[0] * GRID.dims[1] * GRID.dims[2], 97)[None]
    for i in (0, 1):
        logits, confidence, labels, wire = forward(training_sample(CFG, "ego")(data, i), index, np.random.default_rng())
        assert wire == {}  # no wire code outside the wire stage
        assert logits[-1].shape[-1] == index.shape[1] and confidence.shape[1] == 1 and labels.shape == GRID.dims
    assert scans == [MERGED[0], MERGED[1]]
