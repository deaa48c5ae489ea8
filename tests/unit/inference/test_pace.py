"""The demo's playback rate from a frame's measured cost (model.pace)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from model_checks import MICRO

from co3sop_nodes.inference import pace
from co3sop_nodes.inference.inputs import lidar_occupancy
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.path import inference_path


def test_the_rate_is_bound_by_the_cores_and_by_the_ego():
    cost = pace.FrameCost(vehicle_s=0.05, ego_s=0.1)
    h = pace.HEADROOM
    # 3 vehicles + ego = 0.25 s of CPU per frame on 2 cores: 0.125 s per frame, with headroom, for a 0.1 s frame
    assert pace.sustainable_rate(cost, 3, 0.1, 2) == pytest.approx(0.1 / (0.125 * h))
    # on many cores the ego, one process that handles every frame in turn, is the bound
    assert pace.sustainable_rate(cost, 3, 0.1, 64) == pytest.approx(0.1 / (0.1 * h))
    assert pace.sustainable_rate(cost, 6, 0.1, 2) < pace.sustainable_rate(cost, 3, 0.1, 2)  # more vehicles, slower
    assert pace.sustainable_rate(pace.FrameCost(0.001, 0.001), 3, 0.1, 2) == 1.0  # never faster than real time
    # the ego encoding its two neighbours' scans: 0.1 + 2 x 0.05 s a frame, more than the 0.35 s of CPU over 2 cores
    assert pace.sustainable_rate(cost, 3, 0.1, 2, scans=True) == pytest.approx(0.1 / (0.2 * h))
    assert pace.sustainable_rate(cost, 3, 0.1, 2, egos=3, scans=True) < pace.sustainable_rate(cost, 3, 0.1, 2, egos=3)
    # the recorder's pictures of each ego's prediction count towards the CPU, not towards the ego's own time
    drawn = pace.FrameCost(vehicle_s=0.05, ego_s=0.1, recording_s=0.02)
    # 3 x 0.05 + 2 x (0.1 + 0.02) = 0.39 s of CPU over 2 cores
    assert pace.sustainable_rate(drawn, 3, 0.1, 2, egos=2) == pytest.approx(0.1 / (0.39 / 2 * h))
    assert pace.sustainable_rate(drawn, 3, 0.1, 64) == pytest.approx(0.1 / (0.1 * h))
    # what the demo says binds
    assert pace.rate_bound(cost, 3, 2) == "the frame's CPU over the cores"
    assert pace.rate_bound(cost, 3, 64) == pace.rate_bound(cost, 3, 2, scans=True) == "one ego's frame"
    assert pace.rate_bound(pace.FrameCost(vehicle_s=0.2, ego_s=0.1), 3, 64) == "one vehicle's frame"


@pytest.mark.parametrize(
    ("measured", "sustained"),
    [
        # the demo's measured costs (vehicle, ego, pictures) on two CPUs, and the highest rate at which their graph
        # fused every frame of 100 in bench_graph's runs (BENCHMARKS.md)
        (pace.FrameCost(0.016, 0.047, 0.004), 1.0),  # AVX-512 BF16, family 26: 1.0 in most runs
        (pace.FrameCost(0.026, 0.076, 0.005), 0.67),  # AVX-512 BF16, family 25: 0.67 in two of three, 0.8 in none
        (pace.FrameCost(0.020, 0.068, 0.003), 0.8),  # family 25, the vehicles on int8 (auto): 0.8, 1.0 in none
        (pace.FrameCost(0.0177, 0.0666, 0.0019), 0.9),  # the same, their output dequantized in one copy: 0.9
    ],
)
def test_the_rate_stays_within_what_the_measured_graphs_sustained(measured, sustained):
    rate = pace.sustainable_rate(measured, 3, 0.1, 2)
    assert rate <= sustained
    assert rate > 0.85 * sustained  # not so cautious that a machine plays far below what it keeps up with


@pytest.mark.parametrize("name", ["tiny", "tiny-lidar"])
def test_a_frame_is_measured_for_both_modalities(name):
    model = build_model(preset(name, **MICRO)).eval()
    cost = pace.frame_cost(model, repeats=1)
    assert 0 < cost.vehicle_s < 10 and 0 < cost.ego_s < 10 and 0 < cost.recording_s < 10
    inputs = pace.shaped_inputs(model)
    assert set(inputs) == ({"occupancy"} if name == "tiny-lidar" else {"images", "lidar2img"})


def test_a_lidar_model_is_measured_on_the_scan_given():
    """The first layer's work grows with the voxels hit: the vehicle runs on the bag's scan, voxelised as a vehicle
    node voxelises it."""
    model = build_model(preset("tiny-lidar", **MICRO)).eval()
    scan = np.random.default_rng(0).uniform(-30, 30, (5000, 3)) * [1, 1, 0.05]
    occupancy = pace.shaped_inputs(model, scan=scan)["occupancy"]
    assert torch.equal(occupancy, torch.from_numpy(lidar_occupancy(scan, model.cfg.grid))[None])
    assert 0 < occupancy.sum() < 5000
    assert 0 < pace.frame_cost(model, repeats=1, scan=scan).vehicle_s < 10


def test_warm_up_runs_both_halves_on_the_cpu(monkeypatch):
    model = build_model(preset("tiny", **MICRO)).eval()
    calls = []
    monkeypatch.setattr(
        model.ego, "fuse", lambda *a, **k: calls.append("fuse") or model.ego.__class__.fuse(model.ego, *a, **k)
    )
    assert pace.warm_up(model, ego=False) > 0 and calls == []  # a vehicle: its half only
    assert pace.warm_up(model, ego=True) > 0 and calls == ["fuse"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (CI has none)")
def test_warm_up_on_a_gpu_runs_both_halves():
    model = build_model(preset("tiny", **MICRO)).eval().use(inference_path("cuda", "float32"))
    assert pace.warm_up(model, ego=True) > 0


def test_the_vehicle_is_measured_on_the_vehicle_nodes_own_model(monkeypatch):
    """Vehicle nodes on a path of their own (auto: int8 for a vehicle half tuned for it) run a copy on it: the
    vehicle's cost is that copy's, the ego's the model's."""
    model, vehicles = (build_model(preset("tiny-lidar", **MICRO)).eval() for _ in range(2))
    calls = {"model": 0, "vehicles": 0}
    for name, m in (("model", model), ("vehicles", vehicles)):
        original = m.vehicle.forward
        monkeypatch.setattr(
            m.vehicle, "forward", lambda *a, n=name, f=original, **kw: calls.update({n: calls[n] + 1}) or f(*a, **kw)
        )
    pace.frame_cost(model, repeats=3, vehicles=vehicles)
    assert calls["model"] == 1 and calls["vehicles"] >= 3  # the model: the ego's own features, untimed
