"""How fast this machine can play a bag through the graph: a model's CPU cost per frame, measured (ROS-free).

The demo plays its bag at the rate the machine keeps up with: every vehicle
runs its half once per frame and the ego fuses and labels it, each process on
one thread, all processes sharing the machine's cores. The frame's cost is
measured here on inputs of the real shapes (random images through the OPV2V
rig, or a LiDAR-like occupancy), since the work of every stage depends on the
shapes, not the values.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from co3sop_nodes.common.frames import CameraFrame
from co3sop_nodes.inference.inputs import camera_inputs, sensor_inputs, to_batch
from co3sop_nodes.inference.outputs import encode_output
from co3sop_nodes.inference.predict import predict_frame
from co3sop_nodes.model.co3sop import Co3SOP, VehicleOutput
from co3sop_nodes.sim import rig
from co3sop_nodes.v2x.codec import FeatureCodecConfig, encode_labels
from co3sop_nodes.viz.cloud import occupancy_cloud

# The graph's CPU a frame over the work measured here: DDS, the nodes' message conversions, the player and the
# recorder writing. bench_graph measured 1.55 on an AVX-512 BF16 CPU at 1.0 and 1.29-1.54 on one with half its
# bfloat16 throughput (the higher in a slow spell): a ratio, as the overheads scale with the machine
# (BENCHMARKS.md, "The demo's rate on a CPU with half the bfloat16 throughput"). On AMD's family 26, with int8 nodes
# whose work shrinks more than the nodes' own costs, 1.51-2.39, while the graph fused every frame at 78-88 % of the
# cores, above UTILISATION: HEADROOM, their ratio, held there ("The player reads ahead").
OVERHEAD = 1.55
# The share of the cores the graph may keep busy on average and still fuse every frame: its processes wake together
# at each frame, and a slow spell of a shared machine costs a frame. On 2 cores, with the nodes' memory reserved at
# configure, every frame of 100 was fused at 76-82 % in two runs of three and 99 in the third; at 84-93 % frames
# were skipped (BENCHMARKS.md, "Memory reserved at configure" and the section above).
UTILISATION = 0.8
# play at 1 / HEADROOM of the rate the measured work allows
HEADROOM = OVERHEAD / UTILISATION


@dataclass(frozen=True)
class FrameCost:
    vehicle_s: float  # one vehicle half + the feature codec (default settings), one thread
    ego_s: float  # fusion of the ego and 2 neighbours, head to labels and their encoding, one thread
    recording_s: float = 0.0  # the recorder's pictures of a prediction: its points and its ground truth's


def shaped_inputs(model: Co3SOP, seed: int = 0, scan: np.ndarray | None = None) -> dict:
    """VehicleHalf inputs of the model's shapes, on its device: random images seen through the OPV2V rig; for a
    LiDAR model the `scan` (N, 3) given, as a vehicle node voxelises it (the first layer's work grows with the
    voxels hit), else ~3 % of voxels hit."""
    cfg, device = model.cfg, model.path.torch_device
    rng = np.random.default_rng(seed)
    if cfg.modality == "lidar":
        if scan is not None:
            return to_batch(sensor_inputs(cfg, np.eye(4), points=scan), device)
        return to_batch({"occupancy": (rng.random((1, *cfg.grid.dims)) < 0.03).astype(np.uint8)}, device)
    w, h = cfg.image_size
    cams = [
        CameraFrame(name, mount, rig.intrinsics(w, h), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
        for name, mount in zip(rig.CAMERA_NAMES, rig.vehicle_from_cameras())
    ]
    images, lidar2img = camera_inputs(cams, rig.vehicle_from_lidar(), cfg.image_size)
    return to_batch({"images": images, "lidar2img": lidar2img}, device)


def shaped_neighbours(own: VehicleOutput) -> dict[int, tuple[VehicleOutput, np.ndarray]]:
    """Two neighbours 10 m ahead and behind whose outputs are `own`'s, shifted by 3 and 6 voxels along y:
    predict_frame's candidates."""
    others = {}
    for i, dx in ((1, 10.0), (2, -10.0)):
        pose = np.eye(4)
        pose[0, 3] = dx
        others[i] = (VehicleOutput(own.features.roll(3 * i, 2), own.confidence.roll(3 * i, 2)), pose)
    return others


@torch.inference_mode()
def warm_up(model: Co3SOP, ego: bool) -> float:
    """A vehicle half (and with `ego`, a fusion of 2 neighbours and the head) on inputs of the model's shapes, so
    that no frame waits for what a device does on first use: on a GPU, loading kernels and choosing cuDNN algorithms
    (seconds); on a CPU, oneDNN's kernels made for each shape and the first allocations (tens of ms, on a graph's
    first and busiest frames); nodes call it before they say they are ready. The seconds it took."""
    t0 = time.perf_counter()
    own = model.vehicle(**shaped_inputs(model))
    if ego:
        predict_frame(model, own, np.eye(4), shaped_neighbours(own))
    if model.path.torch_device.type == "cuda":
        torch.cuda.synchronize(model.path.torch_device)
    return time.perf_counter() - t0


def _median_cpu(fn, repeats: int) -> tuple[float, object]:
    """Median CPU seconds of `repeats` calls of fn after one to warm up, and the last call's result."""
    result = fn()  # warm-up: first-call allocations, the compiled head kernel
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        result = fn()
        times.append(time.process_time() - t0)
    return float(np.median(times)), result


@torch.inference_mode()
def frame_cost(
    model: Co3SOP, repeats: int = 9, scan: np.ndarray | None = None, vehicles: Co3SOP | None = None
) -> FrameCost:
    """CPU seconds per frame of a vehicle and of the ego with 2 neighbours 10 m away, on one thread, as the nodes
    compute them (the nodes' conversions of messages excepted); a LiDAR model's vehicle on `scan` where given (a
    scan of the bag to be played: see shaped_inputs), on `vehicles` where the vehicle nodes run a path of their own
    (the same model on it), else on `model`. Medians of `repeats` calls: on a shared machine single calls vary by
    10 % and more, and a median of few lets one slow spell set the demo's rate (under a second at the default)."""
    cfg = model.cfg
    vehicles = model if vehicles is None else vehicles
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        inputs = shaped_inputs(model, scan=scan)
        vehicle_s, _ = _median_cpu(
            lambda: encode_output(vehicles.vehicle(**inputs), cfg.feature_grid, FeatureCodecConfig()), repeats
        )
        ego = model.vehicle(**inputs)
        others = shaped_neighbours(ego)

        def ego_frame():
            pred = predict_frame(model, ego, np.eye(4), others)
            encode_labels(pred.labels, cfg.grid, cfg.num_classes, confidence=pred.confidence)
            return pred.labels

        ego_s, labels = _median_cpu(ego_frame, repeats)
        recording_s, _ = _median_cpu(lambda: [occupancy_cloud(labels, cfg.grid) for _ in range(2)], repeats)
    finally:
        torch.set_num_threads(threads)
    return FrameCost(vehicle_s, ego_s, recording_s)


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def graph_work(cost: FrameCost, vehicles: int, egos: int = 1, scans: bool = False) -> tuple[float, float]:
    """The CPU seconds a frame of the graph takes in the work measured here (every vehicle's half, every ego's frame
    and the recorder's pictures of it), and one ego's. With `scans` the vehicles send their scans and each ego runs
    the vehicle half once per neighbour too."""
    ego_s = cost.ego_s + (vehicles - 1) * cost.vehicle_s if scans else cost.ego_s
    return vehicles * cost.vehicle_s + egos * (ego_s + cost.recording_s), ego_s


def sustainable_rate(
    cost: FrameCost,
    vehicles: int,
    period_s: float,
    n_cores: int,
    headroom: float = HEADROOM,
    egos: int = 1,
    scans: bool = False,
) -> float:
    """The playback rate (1 = real time) at which the graph keeps up: the frame's CPU over the cores (graph_work),
    and an ego (one process, every frame in turn) each bound the wall time per frame; with headroom, at most real
    time."""
    wall = max(_bounds(cost, vehicles, n_cores, egos, scans).values()) * headroom
    return float(min(1.0, period_s / wall))


def rate_bound(cost: FrameCost, vehicles: int, n_cores: int, egos: int = 1, scans: bool = False) -> str:
    """What bounds `sustainable_rate`, in words."""
    bounds = _bounds(cost, vehicles, n_cores, egos, scans)
    return max(bounds, key=bounds.get)


def _bounds(cost: FrameCost, vehicles: int, n_cores: int, egos: int, scans: bool) -> dict[str, float]:
    """Each bound on the wall time of a frame, in words -> seconds: the frame's CPU over the cores, and an ego's and
    a vehicle's frame (each one process that takes every frame in turn)."""
    cpu, ego_s = graph_work(cost, vehicles, egos, scans)
    return {
        "the frame's CPU over the cores": cpu / max(1, n_cores),
        "one ego's frame": ego_s,
        "one vehicle's frame": cost.vehicle_s,
    }
