"""Model benchmark: CPU time per stage at each range, masked vs dense fusion, peak memory.

    ros2_ws/benchmarks/bench_model.py [--preset tiny] [--repeats 3] [--out FILE.md]

Run with the workspace environment (`. ros2_ws/env.sh`). For the preset at each
benchmark range (untrained weights: timing does not depend on them), with
random camera images and 2 collaborators: seconds for the vehicle half per
agent, the warp per neighbour, the fusion, the head; the head's dense
reference (logits at every scale, softmax, argmax) against its exact fast path
(`OccupancyHead.labels`), measured in the same run; then the fusion computed
only where the hybrid mask selects against the dense reference, on the same
inputs (outputs compared on the selected voxels), for several mask densities;
and the process's peak resident memory. The accuracy cost of each feature
codec comes from `evaluate --ablation codec` on a trained model.
"""

from __future__ import annotations

import argparse
import resource
from pathlib import Path

import numpy as np
import torch

from co3sop_nodes.model.config import preset
from co3sop_nodes.frames import CameraFrame
from co3sop_nodes.model.inputs import camera_inputs, to_batch
from co3sop_nodes.model.model import VehicleOutput, build_model
from co3sop_nodes.model.outputs import labels_from_logits
from co3sop_nodes.model.warp import warp_with_mask
from co3sop_nodes.sim import rig
from timing import timed


def random_camera_inputs(cfg) -> dict:
    """Random images seen through the OPV2V rig, at the config's image size."""
    w, h = cfg.image_size
    rng = np.random.default_rng(0)
    cams = [CameraFrame(name, mount, rig.intrinsics(w, h), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
            for name, mount in zip(rig.CAMERA_NAMES, rig.vehicle_from_cameras())]
    images, lidar2img = camera_inputs(cams, rig.vehicle_from_lidar(), cfg.image_size)
    return to_batch({"images": images, "lidar2img": lidar2img})


@torch.no_grad()
def stage_table(name: str, repeats: int) -> str:
    rows = ["| range | feature grid | vehicle half s/agent | warp s/neighbour | fusion s | head s | total s (ego + 2 collaborators) |",
            "|---|---|---:|---:|---:|---:|---:|"]
    for range_name in ("25.6m", "51.2m", "76.8m"):
        cfg = preset(name, range=range_name)
        model = build_model(cfg).eval()
        inputs = random_camera_inputs(cfg)
        t_vehicle, ego = timed(lambda: model.vehicle(**inputs), repeats)
        others = [VehicleOutput(ego.features.roll(3, 2), torch.rand_like(ego.confidence)) for _ in range(2)]
        rel = torch.eye(4)[None].repeat(1, 2, 1, 1)
        rel[0, :, 0, 3] = torch.tensor([6.0, -9.0])
        t_warp, _ = timed(lambda: warp_with_mask(torch.cat([others[0].features, others[0].confidence], 1), rel[:, 0], cfg.feature_grid), repeats)
        t_fuse, fused = timed(lambda: model.ego.fuse(ego, others, rel), repeats)
        t_head, _ = timed(lambda: model.ego.head(fused), repeats)
        total = 3 * t_vehicle + 2 * t_warp + t_fuse + t_head
        rows.append(f"| {range_name} | {'x'.join(map(str, cfg.feature_grid.dims))} | {t_vehicle:.3f} | {t_warp:.4f} | {t_fuse:.3f} | {t_head:.3f} | {total:.2f} |")
        print(f"  {range_name}: vehicle {t_vehicle:.3f} s, fusion {t_fuse:.3f} s, head {t_head:.3f} s", flush=True)
    return "\n".join(rows)


@torch.no_grad()
def head_table(name: str, repeats: int) -> str:
    """Fused features -> labels + confidence: the dense reference against the exact fast path, same inputs, same run."""
    rows = ["| range | label grid | reference s (dense logits, softmax, argmax) | fast s (`head.labels`) | reference / fast | labels identical |",
            "|---|---|---:|---:|---:|---|"]
    for range_name in ("25.6m", "51.2m", "76.8m"):
        cfg = preset(name, range=range_name)
        head = build_model(cfg).ego.head.eval()
        fused = torch.randn(1, cfg.embed_dims, *cfg.feature_grid.dims, generator=torch.Generator().manual_seed(0))
        t_ref, (ref_labels, _) = timed(lambda: labels_from_logits(head(fused)[-1]), repeats)
        t_fast, (labels, _) = timed(lambda: head.labels(fused), repeats)
        same = bool((labels[0].numpy() == ref_labels).all())
        rows.append(f"| {range_name} | {'x'.join(map(str, cfg.grid.dims))} | {t_ref:.3f} | {t_fast:.3f} | {t_ref / t_fast:.1f}x | {'yes' if same else 'NO'} |")
        print(f"  head {range_name}: reference {t_ref:.3f} s, fast {t_fast:.3f} s", flush=True)
    return "\n".join(rows)


@torch.no_grad()
def masked_table(name: str, repeats: int) -> str:
    cfg = preset(name)
    model = build_model(cfg).eval()
    fusion = model.ego.fusion
    c, dims = cfg.embed_dims, cfg.feature_grid.dims
    rows = ["| selected voxels | masked s | dense s | dense / masked | max abs difference on selected |", "|---:|---:|---:|---:|---:|"]
    for share in (0.05, 0.2, 0.5, 1.0):
        gen = torch.Generator().manual_seed(0)
        ego = torch.randn(1, c, *dims, generator=gen)
        values = torch.randn(1, 2, c, *dims, generator=gen)
        mask = torch.rand(1, 2, *dims, generator=gen) < share / 2 if share < 1 else torch.ones(1, 2, *dims, dtype=torch.bool)
        t_masked, masked = timed(lambda: fusion(ego, values, mask), repeats)
        t_dense, dense = timed(lambda: fusion(ego, values, mask, dense=True), repeats)
        selected = mask.any(1)[:, None].expand_as(masked)
        diff = float((masked - dense)[selected].abs().max())
        rows.append(f"| {float(mask.any(1).float().mean()):.1%} | {t_masked:.3f} | {t_dense:.3f} | {t_dense / t_masked:.1f}x | {diff:.1e} |")
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path)
    opts = parser.parse_args()
    torch.set_num_threads(opts.threads)
    text = "\n\n".join([
        f"### CPU time per stage, preset `{opts.preset}` ({opts.threads} threads, median of {opts.repeats})", stage_table(opts.preset, opts.repeats),
        f"### Head to labels: dense reference vs exact fast path (`{opts.preset}`)", head_table(opts.preset, opts.repeats),
        f"### Masked vs dense fusion attention (`{opts.preset}`, 51.2 m, 2 collaborators)", masked_table(opts.preset, opts.repeats),
        f"Peak resident memory of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB.",
    ])
    print(text)
    if opts.out:
        opts.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
