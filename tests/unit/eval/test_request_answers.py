"""Offline request maps as the graph sends them: their levels, and a sender's answer for each ego or one for all."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from memory_dataset import MemoryDataset

from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.eval import evaluate as evaluation
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import LidarConfig, preset
from co3sop_nodes.train.dataset import AgentRecord
from co3sop_nodes.v2x.codec import FeatureCodecConfig
from co3sop_nodes.v2x.request_map import request_for_neighbour
from co3sop_nodes.v2x.sender_requests import union_request

GRID = GridSpec((-6.4, -6.4, -2.0), 0.4, (32, 32, 8))
CFG = preset(
    "tiny-lidar",
    custom_grid=(GRID.origin, GRID.voxel_size, GRID.dims),
    lidar=LidarConfig("sscnet", 8),
    embed_dims=8,
    head_channels=(8, 8, 8),
)
CODEC = FeatureCodecConfig("int8", "request", max_bytes=4096)


def dataset() -> MemoryDataset:
    """One scenario of two frames; three agents 2 m apart, moving 1 m per frame."""
    rng = np.random.default_rng(0)
    frames = []
    for t in (0, 1):
        records = []
        for j in range(3):
            pose = np.eye(4)
            pose[:2, 3] = 2.0 * j + t, 0.5 * j
            occupancy = (rng.random((1, *GRID.dims)) < 0.05).astype(np.uint8)
            records.append(AgentRecord(j, pose, {"occupancy": occupancy}, np.zeros(GRID.dims, np.uint8)))
        frames.append((("test", "s0", t), records))
    return MemoryDataset(frames, CFG)


@pytest.fixture
def encoded(monkeypatch):
    """Every message the evaluation encodes: (frame's sender pose, the request it weighs)."""
    sent, real = [], evaluation.through_codec

    def recorded(out, grid, cfg, request=None):
        sent.append(request)
        return real(out, grid, cfg, request)

    monkeypatch.setattr(evaluation, "through_codec", recorded)
    return sent


def test_one_message_for_all_egos_weighs_the_union_of_their_requests(encoded):
    torch.manual_seed(0)
    model, data = build_model(CFG).eval(), dataset()
    cache = evaluation.vehicle_cache()
    evaluation.evaluate(model, data, codec=CODEC, cache=cache, request_answer="each")
    each = list(encoded)
    encoded.clear()
    evaluation.evaluate(model, data, codec=CODEC, cache=cache, request_answer="union")
    union = list(encoded)
    # frame 0: no request yet, a message per ego either way (3 egos x 2 senders); frame 1: each, a message per
    # (ego, sender) pair; union, one per sender
    assert len(each) == 12 and len(union) == 6 + 3
    assert all(r is None for r in each[:6] + union[:6])
    grid, frame = CFG.feature_grid, data.frames[1]
    requests = {}
    for j in range(3):  # each agent's request of frame 0, as the vehicles receive it (256 levels)
        out = cache[(0, j, "real")]
        requests[j] = (
            evaluation.decode_request(evaluation.encode_request(evaluation.request_of(out.confidence), grid)),
            data.frames[0].poses[j],
        )
    for sender in range(3):  # in the order the samples first need them
        asks = [request_for_neighbour(*requests[e], frame.poses[sender], grid) for e in range(3) if e != sender]
        assert sum(np.array_equal(got, union_request(asks)) for got in union[6:]) == 1


def test_requests_reach_the_vehicles_with_the_egos_levels(monkeypatch):
    levels, real = [], evaluation.encode_request

    def recorded(need, grid, *args, **kwargs):
        levels.append(kwargs.get("levels"))
        return real(need, grid, *args, **kwargs)

    monkeypatch.setattr(evaluation, "encode_request", recorded)
    torch.manual_seed(0)
    evaluation.evaluate(build_model(CFG).eval(), dataset(), codec=CODEC, request_levels=2)
    assert levels and set(levels) == {2}


def test_a_frame_answers_the_request_of_its_own_frame_where_it_waits_for_it(encoded):
    """request_frame "current": every frame, the first included, weighs each ego's map of that same frame."""
    torch.manual_seed(0)
    model, data = build_model(CFG).eval(), dataset()
    cache = evaluation.vehicle_cache()
    evaluation.evaluate(model, data, codec=CODEC, cache=cache, request_frame="current")
    assert len(encoded) == 12 and all(r is not None for r in encoded)  # 2 frames x 3 egos x 2 senders
    grid = CFG.feature_grid
    for t, frame in enumerate(data.frames):
        for ego in range(3):
            out = cache[(t, ego, "real")]
            need = evaluation.decode_request(evaluation.encode_request(evaluation.request_of(out.confidence), grid))
            for sender in (s for s in range(3) if s != ego):
                wanted = request_for_neighbour(need, frame.poses[ego], frame.poses[sender], grid)
                assert sum(np.array_equal(got, wanted) for got in encoded) >= 1
    with pytest.raises(evaluation.Co3sopError, match="request_frame 'next'"):
        evaluation.evaluate(model, data, codec=CODEC, cache=cache, request_frame="next")
