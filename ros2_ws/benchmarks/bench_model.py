"""Model benchmark: CPU time per stage at each range, masked vs dense fusion, peak memory.

    ros2_ws/benchmarks/bench_model.py [--preset tiny] [--repeats 3] [--out FILE.md] [--device cuda]

Run with the workspace environment (`. ros2_ws/env.sh`). For the preset at each
benchmark range (untrained weights: timing does not depend on them), with
random camera images and 2 collaborators: seconds for the vehicle half per
agent, the warp per neighbour, the fusion, the head; the head's dense
reference (logits at every scale, softmax, argmax) against its exact fast path
(`OccupancyHead.labels`), measured in the same run; then the fusion computed
only where the hybrid mask selects against the dense reference, on the same
inputs (outputs compared on the selected voxels), for several mask densities;
and the process's peak resident memory. With `--device cuda` the stages, the
head and the fusion run on the GPU (the warp on its PyTorch path, the per-node
CPU table is left out) and the peak GPU memory is given. The accuracy cost of each feature
codec comes from `evaluate --ablation codec` on a trained model.
"""

from __future__ import annotations

import argparse
import itertools
import resource
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from timing import alternated, timed
from torch.utils.flop_counter import FlopCounterMode

from co3sop_nodes import kernels
from co3sop_nodes.cli.device import add_device_argument
from co3sop_nodes.common.allocation import keep_freed_memory
from co3sop_nodes.data.bags import read_scans
from co3sop_nodes.inference import pace
from co3sop_nodes.inference.checkpoint import load_model, shipped_checkpoint
from co3sop_nodes.inference.inputs import lidar_occupancy, lidar_occupancy_reference
from co3sop_nodes.inference.outputs import labels_from_logits
from co3sop_nodes.inference.predict import predict_frame
from co3sop_nodes.kernels.warp import warp_compiled, warp_with_mask
from co3sop_nodes.model import quantized
from co3sop_nodes.model.co3sop import VehicleOutput, build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.conv_norm import folded, z_outer
from co3sop_nodes.model.path import PRECISIONS, InferencePath, cpu_bfloat16_unit, inference_path, resolve_device


def on(device: torch.device):
    """`timed` for work on `device`: a CUDA call is timed until the GPU has finished it."""
    if device.type != "cuda":
        return timed

    def timed_synchronised(fn, repeats):
        def call():
            result = fn()
            torch.cuda.synchronize(device)
            return result

        call()  # warm-up: cuDNN's algorithm choice, the caching allocator
        return timed(call, repeats)

    return timed_synchronised


@torch.no_grad()
def stage_table(name: str, repeats: int, device: torch.device) -> str:
    rows = [
        "| range | feature grid | vehicle half s/agent | warp s/neighbour | fusion s | head s | total s (ego "
        "+ 2 collaborators) |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for range_name in ("25.6m", "51.2m", "76.8m"):
        cfg = preset(name, range=range_name)
        model = build_model(cfg).eval().to(device)
        inputs = {k: v.to(device) for k, v in pace.shaped_inputs(model).items()}
        timed_on = on(device)
        t_vehicle, ego = timed_on(lambda: model.vehicle(**inputs), repeats)
        others = [VehicleOutput(ego.features.roll(3, 2), torch.rand_like(ego.confidence)) for _ in range(2)]
        rel = torch.eye(4)[None].repeat(1, 2, 1, 1)
        rel[0, :, 0, 3] = torch.tensor([6.0, -9.0])
        rel = rel.to(device)
        if device.type == "cpu":
            t_warp, _ = timed(
                lambda: warp_compiled(
                    others[0].features, others[0].confidence, rel[:, 0], cfg.feature_grid, torch.get_num_threads()
                ),
                repeats,
            )
        else:
            both = torch.cat([others[0].features, others[0].confidence], 1)
            t_warp, _ = timed_on(lambda: warp_with_mask(both, rel[:, 0], cfg.feature_grid), repeats)
        t_fuse, fused = timed_on(lambda: model.ego.fuse(ego, others, rel), repeats)
        t_head, _ = timed_on(lambda: model.ego.head.labels(fused), repeats)
        total = 3 * t_vehicle + 2 * t_warp + t_fuse + t_head
        rows.append(
            f"| {range_name} | {'x'.join(map(str, cfg.feature_grid.dims))} | {t_vehicle:.3f} | {t_warp:.4f} | "
            f"{t_fuse:.3f} | {t_head:.3f} | {total:.2f} |"
        )
        print(f"  {range_name}: vehicle {t_vehicle:.3f} s, fusion {t_fuse:.3f} s, head {t_head:.3f} s", flush=True)
    return "\n".join(rows)


@torch.no_grad()
def head_table(name: str, repeats: int, device: torch.device) -> str:
    """Fused features -> labels + confidence: the dense reference, the PyTorch loop and the compiled kernel (on the
    CPU), same run."""
    if device.type == "cuda":
        return gpu_head_table(name, repeats, device)
    rows = [
        "| range | label grid | reference s (dense logits, softmax, argmax) | PyTorch loop s | compiled s | "
        "reference / compiled "
        "| loop / compiled | labels differing (loop, compiled) |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for range_name in ("25.6m", "51.2m", "76.8m"):
        cfg = preset(name, range=range_name)
        head = build_model(cfg).ego.head.eval()
        fused = torch.randn(1, cfg.embed_dims, *cfg.feature_grid.dims, generator=torch.Generator().manual_seed(0))
        t_ref, (ref_labels, _) = timed(lambda: labels_from_logits(head(fused)[-1]), repeats)
        t_loop, (loop, _) = timed(lambda: head.labels(fused, compiled=False), repeats)
        t_fast, (fast, _) = timed(lambda: head.labels(fused, compiled=True), repeats)
        differ = [int((t[0].numpy() != ref_labels).sum()) for t in (loop, fast)]
        rows.append(
            f"| {range_name} | {'x'.join(map(str, cfg.grid.dims))} | {t_ref:.3f} | {t_loop:.3f} | "
            f"{t_fast:.3f} | {t_ref / t_fast:.1f}x "
            f"| {t_loop / t_fast:.1f}x | {differ[0]}, {differ[1]} of {ref_labels.size:,} |"
        )
        print(f"  head {range_name}: reference {t_ref:.3f} s, loop {t_loop:.3f} s, compiled {t_fast:.3f} s", flush=True)
    return "\n".join(rows)


def frame_table(repeats: int) -> str:
    """Each shipped model's work per frame on one thread, as the nodes do it, at each range's grid (untrained beyond
    51.2 m: timing depends on shapes only), on the PyTorch paths and with the compiled kernels, same run; and the
    playback rate 2 cores keep up with for 3 vehicles + ego."""
    rows = [
        "| model | range | vehicle ms (model + codec): PyTorch / compiled | ratio | ego ms (2 neighbours, "
        "labels, encoding, cloud): "
        "PyTorch / compiled | ratio | rate kept up with (3 vehicles, 2 cores): PyTorch / compiled |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for name in ("tiny-lidar", "tiny"):
        trained, _ = load_model(shipped_checkpoint(f"{name}.pt"))
        for range_name in ("25.6m", "51.2m", "76.8m"):
            model = (
                trained
                if range_name == trained.cfg.range
                else build_model(replace(trained.cfg, range=range_name)).eval()
            )
            costs = []
            for compiled in (False, True):
                model.use(InferencePath(compiled=compiled))
                costs.append(pace.frame_cost(model, repeats))
            ref, fast = costs
            rates = [pace.sustainable_rate(c, 3, 0.1, 2) for c in costs]
            rows.append(
                f"| {name} | {range_name} | {1e3 * ref.vehicle_s:.0f} / {1e3 * fast.vehicle_s:.0f} | "
                f"{ref.vehicle_s / fast.vehicle_s:.1f}x | "
                f"{1e3 * ref.ego_s:.0f} / {1e3 * fast.ego_s:.0f} | {ref.ego_s / fast.ego_s:.1f}x | "
                f"{rates[0]:.2f} / {rates[1]:.2f} |"
            )
            print(
                f"  frame {name} {range_name}: vehicle {1e3 * ref.vehicle_s:.0f} -> {1e3 * fast.vehicle_s:.0f} ms, "
                f"ego {1e3 * ref.ego_s:.0f} -> {1e3 * fast.ego_s:.0f} ms",
                flush=True,
            )
    return "\n".join(rows)


def bag_scans(bag: Path, grid, count: int = 12) -> list[torch.Tensor]:
    """The first `count` LiDAR scans of a bag, voxelised on `grid` as a vehicle node does: (1, 1, X, Y, Z) uint8."""
    scans = [torch.from_numpy(lidar_occupancy(points, grid))[None] for points in read_scans(bag, count)]
    if not scans:
        raise SystemExit(f"bench_model: error: {bag} holds no PointCloud2 scan")
    return scans


def binning_table(bag: Path, repeats: int) -> str:
    """A LiDAR vehicle's first step: the bag's first 12 scans binned into `tiny-lidar`'s grid, one a call in turn, by
    NumPy's definition and by the compiled kernel (the same voxels, checked), alternating."""
    grid = preset("tiny-lidar").grid
    scans = read_scans(bag, 12)
    if not scans:
        raise SystemExit(f"bench_model: error: {bag} holds no PointCloud2 scan")
    for points in scans:
        assert np.array_equal(lidar_occupancy(points, grid), lidar_occupancy_reference(points, grid))
    groups = {
        name: {"bin": lambda fn=fn, turn=itertools.cycle(scans): fn(next(turn), grid)}
        for name, fn in (("NumPy", lidar_occupancy_reference), ("compiled", lidar_occupancy))
    }
    times = alternated(groups, repeats)
    numpy_s, compiled_s = times["NumPy", "bin"], times["compiled", "bin"]
    return "\n".join(
        [
            "| points a scan (mean) | grid | NumPy ms | compiled ms | NumPy / compiled |",
            "|---:|---|---:|---:|---:|",
            f"| {np.mean([len(s) for s in scans]):.0f} | {'x'.join(map(str, grid.dims))} | {1e3 * numpy_s:.3f} | "
            f"{1e3 * compiled_s:.3f} | {numpy_s / compiled_s:.1f}x |",
        ]
    )


@torch.no_grad()
def precision_table(device: torch.device, precisions: list[str], repeats: int, bag: Path | None = None) -> str:
    """Each shipped model at 51.2 m, as the nodes run it on `device` (its compiled kernels on the CPU): wall time of
    the vehicle half and of the ego's frame (2 neighbours 10 m away, fusion, labels) per precision, with the ratio
    to float32 measured in the same run. Each precision has its own copy of the model, and the copies take turns
    of a few frames each (`timing.alternated`). With `bag`, a LiDAR model's vehicle half runs on the bag's scans in
    turn (the random scan of 3 % hit otherwise)."""
    rows = [
        "| model | precision | vehicle half ms | ego frame ms | vehicle: float32 / this | ego: float32 / this |",
        "|---|---|---:|---:|---:|---:|",
    ]
    finish = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else None
    for name in ("tiny-lidar", "tiny", "small"):
        groups = {}
        for precision in ["float32", *(p for p in precisions if p != "float32")]:
            model, _ = load_model(shipped_checkpoint(f"{name}.pt"))
            model.use(InferencePath(str(device), precision))
            if model.path.precision != precision:  # int8 for a model without int8 layers: its other precision
                print(f"  {name} {precision}: none here, the model runs {model.path.describe()}", flush=True)
                continue
            vehicle = _vehicle_call(model, bag, device)
            ego = vehicle()
            others = pace.shaped_neighbours(ego)
            groups[precision] = {
                "vehicle": vehicle,
                "ego": lambda model=model, ego=ego, others=others: predict_frame(model, ego, np.eye(4), others),
            }
        times = alternated(groups, repeats, finish)
        base_vehicle, base_ego = times["float32", "vehicle"], times["float32", "ego"]
        for precision in groups:
            t_vehicle, t_ego = times[precision, "vehicle"], times[precision, "ego"]
            rows.append(
                f"| {name} | {precision} | {1e3 * t_vehicle:.1f} | {1e3 * t_ego:.1f} | "
                f"{base_vehicle / t_vehicle:.2f}x | {base_ego / t_ego:.2f}x |"
            )
            print(f"  {name} {precision}: vehicle {1e3 * t_vehicle:.1f} ms, ego {1e3 * t_ego:.1f} ms", flush=True)
    return "\n".join(rows)


def _vehicle_call(model, bag: Path | None, device: torch.device):
    """The vehicle half's call as `precision_table` times it: on the bag's scans in turn for a LiDAR model with
    `bag`, on the model's shaped inputs otherwise."""
    if bag is not None and model.cfg.modality == "lidar":
        turn = itertools.cycle([s.to(device) for s in bag_scans(bag, model.cfg.grid)])
        return lambda: model.vehicle(occupancy=next(turn))
    inputs = pace.shaped_inputs(model)
    return lambda: model.vehicle(**inputs)


@torch.no_grad()
def query_rows_table(bag: Path, frames: int) -> str:
    """The shipped `tiny-lidar` ego (bfloat16 where the CPU computes it, else float32; one thread) on `frames` of
    the bag's scans in turn, each frame's count of queries new as in the graph: the fusion's queries padded to
    InferencePath's default query_rows against none (query_rows 1), alternating frame by frame; mean wall time of
    the fusion and of the head, and the labels compared."""
    model, _ = load_model(shipped_checkpoint("tiny-lidar.pt"))
    precision = inference_path("cpu", "auto").precision
    paths = {rows: InferencePath("cpu", precision, query_rows=rows) for rows in (1, InferencePath().query_rows)}
    model.use(paths[1])
    egos = [model.vehicle(occupancy=s) for s in bag_scans(bag, model.cfg.grid, frames)]
    predict_frame(model, egos[0], np.eye(4), pace.shaped_neighbours(egos[0]))  # the nodes' warm-up
    times = {rows: [] for rows in paths}
    for k, ego in enumerate(egos):
        others = pace.shaped_neighbours(ego)
        got = {}
        for rows in sorted(paths, reverse=bool(k % 2)):
            model.use(paths[rows])
            pred = predict_frame(model, ego, np.eye(4), others)
            times[rows].append((pred.fuse_s, pred.head_s))
            got[rows] = (pred.labels, pred.confidence)
        (labels, confidence), (labels_padded, confidence_padded) = got.values()
        if not (np.array_equal(labels, labels_padded) and np.array_equal(confidence, confidence_padded)):
            raise SystemExit(f"bench_model: error: padded queries changed frame {k}'s labels")
    rows = ["| query_rows | fusion ms (mean) | head ms (mean) | ego: fusion + head ms |", "|---:|---:|---:|---:|"]
    for n, ts in times.items():
        fuse, head = (1e3 * float(np.mean(t)) for t in zip(*ts))
        rows.append(f"| {n} | {fuse:.2f} | {head:.2f} | {fuse + head:.2f} |")
    return f"{precision}, {frames} frames, labels and confidence equal\n\n" + "\n".join(rows)


def _flops(fn) -> int:
    """Floating-point operations of the convolutions and matrix products `fn` runs (2 per multiply-add)."""
    with FlopCounterMode(display=False) as counter:
        fn()
    return counter.get_total_flops()


@torch.no_grad()
def peak_table(repeats: int) -> tuple[str, dict[str, float]]:
    """This CPU's throughput on one thread, measured here: a large matrix product and a 3x3x3 convolution of the
    head's size (32 -> 32 channels over 128x128x12), float32 and bfloat16, the convolution contiguous in float32 and
    channels-last in bfloat16 (as oneDNN wants it), then in both precisions on a z-outer volume (conv_norm.z_outer,
    the head's reduced-precision layout: the convolution of the (z, x, y) views, channels-last); per precision, the
    highest of the three is the peak the stages are held against."""
    rows = ["| kernel | float32 GFLOP/s | bfloat16 GFLOP/s | bfloat16 / float32 |", "|---|---:|---:|---:|"]
    gen = torch.Generator().manual_seed(0)
    a, b = torch.randn(1024, 1024, generator=gen), torch.randn(1024, 1024, generator=gen)
    w = torch.randn(32, 32, 3, 3, 3, generator=gen)  # (Cout, Cin, kx, ky, kz)
    x = torch.randn(1, 32, 128, 128, 12, generator=gen)  # (B, C, X, Y, Z)
    last = torch.channels_last_3d

    def product(dtype):
        ta, tb = a.to(dtype), b.to(dtype)
        return lambda: ta @ tb

    def conv(dtype):
        fmt = last if dtype == torch.bfloat16 else torch.contiguous_format
        tx, tw = x.to(dtype).contiguous(memory_format=fmt), w.to(dtype).contiguous(memory_format=fmt)
        return lambda: F.conv3d(tx, tw, padding=1)

    def conv_z_outer(dtype):
        # the bare convolution of the (z, x, y) views, as `folded` runs it on a z-outer volume
        tx, tw = (z_outer(t.to(dtype)).permute(0, 1, 4, 2, 3) for t in (x, w))  # (B, C, Z, X, Y), channels-last
        return lambda: F.conv3d(tx, tw, padding=1)

    conv_flops = 2 * 32 * 32 * 27 * 128 * 128 * 12
    kernels = {
        "matrix product 1024^3": (product, 2 * 1024**3),
        "conv3d 3x3x3, 32->32, 128x128x12": (conv, conv_flops),
        "conv3d 3x3x3, 32->32, 128x128x12, z-outer": (conv_z_outer, conv_flops),
    }
    peak = {"float32": 0.0, "bfloat16": 0.0}
    for name, (make, flops) in kernels.items():
        rates = []
        for dtype in (torch.float32, torch.bfloat16):
            call = make(dtype)
            call()
            t, _ = timed(call, repeats)
            rates.append(flops / t / 1e9)
        peak = {"float32": max(peak["float32"], rates[0]), "bfloat16": max(peak["bfloat16"], rates[1])}
        rows.append(f"| {name} | {rates[0]:.0f} | {rates[1]:.0f} | {rates[1] / rates[0]:.2f}x |")
        print(f"  peak {name}: float32 {rates[0]:.0f}, bfloat16 {rates[1]:.0f} GFLOP/s", flush=True)
    return "\n".join(rows), peak


@torch.no_grad()
def int8_table(repeats: int, peak: dict[str, float]) -> str:
    """What this CPU's int8 unit (VNNI where it has one) computes on one thread, against the peak of the float
    precision the int8 path computes the rest in (bfloat16 where the CPU computes it, else float32): the
    1024^3 matrix product (torch._int_mm, int32 sums) and the head's 3x3x3 convolution by the int8 path's layer
    (model/quantized.py: oneDNN's quantized convolution, channels-last uint8 activations, per-channel int8 weights,
    requantized to uint8), on a volume stored (x, y, z) and on a z-outer one (the path's layout)."""
    floats = InferencePath(precision="int8").floats
    rows = [f"| kernel | int8 GOP/s | int8 / {floats} peak |", "|---|---:|---:|"]
    gen = torch.Generator().manual_seed(0)
    a, b = (torch.randint(-128, 128, (1024, 1024), generator=gen, dtype=torch.int8) for _ in range(2))
    conv3d, norm = torch.nn.Conv3d(32, 32, 3, padding=1), torch.nn.BatchNorm3d(32).eval()  # norm: the identity
    layer = quantized.Int8ConvReLU.folded(conv3d, norm, 1 / 255, 0.1)
    values = torch.randint(0, 256, (1, 32, 128, 128, 12), generator=gen, dtype=torch.uint8)  # (B, C, X, Y, Z)

    def conv(z_outer_views: bool):
        # the path's layer on the (z, x, y) views of a z-outer volume, or on the volume's own (x, y, z) order: the
        # same convolution's work either way (cubic taps)
        v = values.permute(0, 1, 4, 2, 3) if z_outer_views else values
        x = quantized.Int8Volume(v.contiguous(memory_format=torch.channels_last_3d), 1 / 255)
        return lambda: layer(x)

    conv_ops = 2 * 32 * 32 * 27 * 128 * 128 * 12
    kernels = {
        "matrix product 1024^3": (lambda: torch._int_mm(a, b), 2 * 1024**3),
        "conv3d 3x3x3, 32->32, 128x128x12": (conv(False), conv_ops),
        "conv3d 3x3x3, 32->32, 128x128x12, z-outer": (conv(True), conv_ops),
    }
    for name, (call, ops) in kernels.items():
        call()
        t, _ = timed(call, repeats)
        rate = ops / t / 1e9
        rows.append(f"| {name} | {rate:.0f} | {rate / peak[floats]:.2f}x |")
        print(f"  int8 {name}: {rate:.0f} GOP/s", flush=True)
    return "\n".join(rows)


@torch.no_grad()
def layout_table(repeats: int) -> str:
    """`tiny-lidar`'s 3x3x3 convolutions at 51.2 m (the head's 32 -> 32 channels at 1/4 and 16 -> 16 at 1/2, the LiDAR
    vehicle half's dilated 32 -> 32 at 1/4) in bfloat16 (float32 on a CPU that does not compute bfloat16) on one
    thread, on channels-last volumes against z-outer ones
    (conv_norm.z_outer: the same tensor, z the outermost spatial axis in memory), the two calls alternating so that
    both see the same machine."""
    rows = ["| convolution | channels-last ms | z-outer ms | channels-last / z-outer |", "|---|---:|---:|---:|"]
    gen = torch.Generator().manual_seed(0)
    dtype = InferencePath(precision="int8").float_dtype  # the precision the paths compute their convolutions in
    dims = preset("tiny-lidar").feature_grid.dims
    for c, scale, dilation, what in (
        (32, 1, 1, "head"),
        (16, 2, 1, "head"),
        (32, 1, 2, "LiDAR vehicle half"),
        (32, 1, 3, "LiDAR vehicle half"),
    ):
        shape = tuple(scale * n for n in dims)
        conv = torch.nn.Conv3d(c, c, 3, padding=dilation, dilation=dilation, bias=False).to(dtype)
        x = torch.randn(1, c, *shape, generator=gen).to(dtype)
        last = x.contiguous(memory_format=torch.channels_last_3d)
        outer = z_outer(x)
        norm = torch.nn.BatchNorm3d(c).eval().to(dtype)
        calls = {"last": lambda t=last: folded(conv, norm, t), "outer": lambda t=outer: folded(conv, norm, t)}
        times = {k: [] for k in calls}
        for call in calls.values():
            call()  # oneDNN's kernel for each layout, made once
        for _ in range(max(repeats, 5)):
            for k, call in calls.items():
                t, _ = timed(call, 1)
                times[k].append(t)
        a, b = (1e3 * float(np.median(times[k])) for k in ("last", "outer"))
        name = f"{c} -> {c}, {'x'.join(map(str, shape))}" + (f", dilation {dilation}" if dilation > 1 else "")
        rows.append(f"| {name} ({what}) | {a:.2f} | {b:.2f} | {a / b:.2f}x |")
        print(f"  layout {name}: channels-last {a:.2f} ms, z-outer {b:.2f} ms", flush=True)
    return "\n".join(rows)


@torch.no_grad()
def roofline_table(repeats: int, peak: dict[str, float]) -> str:
    """Each shipped model's stages at 51.2 m on one thread as the nodes run them (compiled kernels), in float32 and,
    on a CPU that computes it, bfloat16: FLOPs per frame (the convolutions and matrix products, counted on the
    reference paths, which compute the same products), time, GFLOP/s and the share of that precision's measured
    peak."""
    precisions = ("float32", "bfloat16") if cpu_bfloat16_unit() else ("float32",)
    rows = [
        "| model | stage | GFLOP per frame | "
        + " | ".join(f"{p} ms | {p} GFLOP/s | share of the {p} peak" for p in precisions)
        + " |",
        "|---|---|---:|" + "---:|---:|---:|" * len(precisions),
    ]
    for name in ("tiny-lidar", "tiny", "small"):
        model, _ = load_model(shipped_checkpoint(f"{name}.pt"))
        model.requires_grad_(False)  # the FLOP counter's module tracker hooks every tensor that requires a gradient
        inputs = pace.shaped_inputs(model)
        ego = model.vehicle(**inputs)
        others = [VehicleOutput(ego.features.roll(3 * i, 2), ego.confidence.roll(3 * i, 2)) for i in (1, 2)]
        rel = torch.eye(4)[None].repeat(1, 2, 1, 1)
        rel[0, :, 0, 3] = torch.tensor([6.0, -9.0])
        fused = model.ego.fuse(ego, others, rel)
        stages = {
            "vehicle half": lambda: model.vehicle(**inputs),
            "fusion (2 neighbours)": lambda: model.ego.fuse(ego, others, rel),
            "head to labels": lambda: model.ego.head.labels(fused),
        }
        reference = {
            "head to labels": lambda: model.ego.head(fused)[-1]
        }  # the labels path computes the full-resolution logits' products
        for stage, fn in stages.items():
            model.use(InferencePath(compiled=False))
            flops = _flops(reference.get(stage, fn))
            if stage == "head to labels":  # the dense pass's 1/4 and 1/2 classifiers are not on the labels path
                flops -= sum(
                    _flops(lambda c=c, f=f: c(f))
                    for c, f in zip(model.ego.head.classify[:2], model.ego.head.coarse(fused))
                )
            cells = []
            for precision in precisions:
                model.use(InferencePath(precision=precision))
                t, _ = timed(fn, repeats)
                cells.append(f"{1e3 * t:.1f} | {flops / t / 1e9:.0f} | {flops / t / 1e9 / peak[precision]:.0%}")
                print(f"  roofline {name} {stage} {precision}: {flops / 1e9:.2f} GFLOP in {1e3 * t:.1f} ms", flush=True)
            rows.append(f"| {name} | {stage} | {flops / 1e9:.2f} | " + " | ".join(cells) + " |")
        model.use(InferencePath())
    return "\n".join(rows)


@torch.no_grad()
def gpu_head_table(name: str, repeats: int, device: torch.device) -> str:
    """The dense reference against the per-parent PyTorch loop, both on the GPU, same run."""
    rows = [
        "| range | label grid | reference s (dense logits, softmax, argmax) | per-parent loop s | reference / "
        "loop | labels differing |",
        "|---|---|---:|---:|---:|---|",
    ]
    timed_on = on(device)
    for range_name in ("25.6m", "51.2m", "76.8m"):
        cfg = preset(name, range=range_name)
        head = build_model(cfg).ego.head.eval().to(device)
        fused = torch.randn(1, cfg.embed_dims, *cfg.feature_grid.dims, generator=torch.Generator().manual_seed(0)).to(
            device
        )
        t_ref, (ref_labels, _) = timed_on(lambda: labels_from_logits(head(fused)[-1]), repeats)
        t_loop, (loop, _) = timed_on(lambda: head.labels(fused), repeats)
        differ = int((loop[0].cpu().numpy() != ref_labels).sum())
        rows.append(
            f"| {range_name} | {'x'.join(map(str, cfg.grid.dims))} | {t_ref:.4f} | {t_loop:.4f} | "
            f"{t_ref / t_loop:.1f}x | {differ:,} of {ref_labels.size:,} |"
        )
        print(f"  head {range_name}: reference {t_ref:.4f} s, loop {t_loop:.4f} s", flush=True)
    return "\n".join(rows)


@torch.no_grad()
def masked_table(name: str, repeats: int, device: torch.device) -> str:
    cfg = preset(name)
    model = build_model(cfg).eval().to(device)
    fusion = model.ego.fusion
    c, dims = cfg.embed_dims, cfg.feature_grid.dims
    rows = [
        "| selected voxels | masked s | dense s | dense / masked | max abs difference on selected |",
        "|---:|---:|---:|---:|---:|",
    ]
    for share in (0.05, 0.2, 0.5, 1.0):
        gen = torch.Generator().manual_seed(0)
        ego = torch.randn(1, c, *dims, generator=gen).to(device)
        values = torch.randn(1, 2, c, *dims, generator=gen).to(device)
        mask = (
            torch.rand(1, 2, *dims, generator=gen) < share / 2
            if share < 1
            else torch.ones(1, 2, *dims, dtype=torch.bool)
        ).to(device)
        t_masked, masked = on(device)(lambda: fusion(ego, values, mask), repeats)
        t_dense, dense = on(device)(lambda: fusion(ego, values, mask, dense=True), repeats)
        selected = mask.any(1)[:, None].expand_as(masked)
        diff = float((masked - dense)[selected].abs().max())
        rows.append(
            f"| {float(mask.any(1).float().mean()):.1%} | {t_masked:.3f} | {t_dense:.3f} | "
            f"{t_dense / t_masked:.1f}x | {diff:.1e} |"
        )
    return "\n".join(rows)


def vector_unit() -> str:
    """The CPU's widest vectors, which the compiled kernels are built for."""
    flags = kernels.cpu_flags()
    return "AVX-512" if "avx512f" in flags else "AVX2, no AVX-512" if "avx2" in flags else "no AVX2"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path)
    add_device_argument(parser)
    parser.add_argument(
        "--precisions",
        nargs="*",
        choices=PRECISIONS[1:],
        default=[],
        help="also time the shipped models at 51.2 m in these precisions against float32",
    )
    parser.add_argument("--precision-only", action="store_true", help="only the precision table")
    parser.add_argument(
        "--bag", type=Path, help="in the precision table, LiDAR vehicle halves on this bag's scans (a random one else)"
    )
    parser.add_argument(
        "--query-rows",
        type=int,
        metavar="FRAMES",
        help="only the fusion's padded queries against none, on this many of --bag's frames",
    )
    parser.add_argument(
        "--head", action="store_true", help="only the head to labels: dense reference, PyTorch loop, compiled kernel"
    )
    parser.add_argument(
        "--binning", action="store_true", help="only a LiDAR scan's binning into the grid (--bag's scans), one thread"
    )
    parser.add_argument(
        "--roofline",
        action="store_true",
        help="only this CPU's measured peak (one thread), each shipped model's FLOPs and GFLOP/s per stage against "
        "it, what its int8 unit computes, and the 3x3x3 convolutions by memory layout",
    )
    opts = parser.parse_args()
    keep_freed_memory()  # as every node and command-line tool allocates
    torch.set_num_threads(opts.threads)
    device = resolve_device(opts.device, "--device")
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {opts.threads} threads"
    precision = (
        [
            f"### Precision: the shipped models at 51.2 m ({where}, median of {opts.repeats})",
            precision_table(device, opts.precisions, opts.repeats, opts.bag),
        ]
        if opts.precisions
        else []
    )
    if opts.query_rows:
        if opts.bag is None:
            parser.error("--query-rows needs --bag (the frames' scans)")
        torch.set_num_threads(1)
        parts = [
            "### The fusion's queries padded to a multiple of query_rows against none (tiny-lidar, one thread)",
            query_rows_table(opts.bag, opts.query_rows),
        ]
    elif opts.binning:
        if opts.bag is None:
            parser.error("--binning needs --bag (its scans)")
        parts = [
            f"### A LiDAR scan binned into its grid (median of {opts.repeats}, one call a scan)",
            binning_table(opts.bag, opts.repeats),
        ]
    elif opts.head:
        parts = [
            f"### Head to labels: dense reference vs its exact fast paths (`{opts.preset}`, {opts.threads} threads, "
            f"median of {opts.repeats}; {vector_unit()})",
            head_table(opts.preset, opts.repeats, device),
        ]
    elif opts.roofline:
        torch.set_num_threads(1)
        peaks, peak = peak_table(opts.repeats)
        parts = [
            f"### This CPU's peak on one thread (median of {opts.repeats}; "
            f"bfloat16 hardware: {cpu_bfloat16_unit() or 'none'})",
            peaks,
            "### Each stage against it (51.2 m, one thread, compiled kernels)",
            roofline_table(opts.repeats, peak),
            f"### This CPU's int8 unit on one thread (median of {opts.repeats}; the convolution by the int8 path's "
            "layer)",
            int8_table(opts.repeats, peak),
            f"### The 3x3x3 convolutions by memory layout ({InferencePath(precision='int8').floats}, one thread, "
            "alternating calls)",
            layout_table(opts.repeats),
        ]
    elif opts.precision_only:
        parts = precision
    elif device.type == "cuda":
        where = f"{torch.cuda.get_device_name(device)}, median of {opts.repeats}"
        parts = [
            f"### GPU time per stage, preset `{opts.preset}` ({where})",
            stage_table(opts.preset, opts.repeats, device),
            f"### Head to labels on the GPU: dense reference vs the per-parent loop (`{opts.preset}`)",
            head_table(opts.preset, opts.repeats, device),
            f"### Masked vs dense fusion attention on the GPU (`{opts.preset}`, 51.2 m, 2 collaborators)",
            masked_table(opts.preset, opts.repeats, device),
            f"Peak GPU memory: {torch.cuda.max_memory_allocated(device) / 2**30:.2f} GiB.",
        ]
    else:
        parts = [
            f"### CPU time per stage, preset `{opts.preset}` ({opts.threads} threads, median of {opts.repeats})",
            stage_table(opts.preset, opts.repeats, device),
            f"### Head to labels: dense reference vs its exact fast paths (`{opts.preset}`, {opts.threads} threads)",
            head_table(opts.preset, opts.repeats, device),
            "### CPU per frame as the nodes compute it (shipped models, one thread, median)",
            frame_table(opts.repeats),
            f"### Masked vs dense fusion attention (`{opts.preset}`, 51.2 m, 2 collaborators)",
            masked_table(opts.preset, opts.repeats, device),
        ]
    parts += [] if opts.precision_only or opts.roofline else precision
    parts.append(
        f"Peak resident memory of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB."
    )
    text = "\n\n".join(parts)
    print(text)
    if opts.out:
        opts.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
