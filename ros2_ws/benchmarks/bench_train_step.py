"""Training benchmark: seconds per optimisation step of each stage at each range, on real samples.

    ros2_ws/benchmarks/bench_train_step.py --data data/tiny [--preset tiny] [--repeats 5] [--stages ego fusion]
        [--ranges 51.2m] [--device cuda]

Run with the workspace environment (`. ros2_ws/env.sh`) on a split written by
`generate`. Each stage at each benchmark range trains a fresh model (untrained
weights: timing does not depend on them) on the split's first sample (an ego
with all its collaborators) for one warm-up step and then `--repeats` steps,
with `train`'s Trainer and sample fraction; the fusion stage caches the frozen
vehicle outputs after their first use, as `train` does, so its figure is the
steady fusion + head step. On a GPU (`--device cuda`) each cell also gives the
step's peak GPU memory. To compare
two versions of the code, run the script with each on PYTHONPATH (e.g. a
`git worktree` of the older commit) back to back on the same machine.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from timing import timed

from co3sop_nodes.cli.device import add_device_argument
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.path import resolve_device
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.train.trainer import Trainer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--splits", nargs="+", default=["train"])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--stages", nargs="+", default=["ego", "fusion"], choices=["ego", "fusion", "joint"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sample-fraction", type=float, default=0.15)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--ranges", nargs="+", default=list(BENCHMARK_RANGES), choices=list(BENCHMARK_RANGES))
    add_device_argument(parser)
    opts = parser.parse_args()
    torch.set_num_threads(opts.threads)
    device = resolve_device(opts.device, "--device")
    gpu = device.type == "cuda"
    rows = ["| stage | " + " | ".join(opts.ranges) + " |", "|---|" + "---:|" * len(opts.ranges)]
    for stage in opts.stages:
        cells = []
        for name in opts.ranges:
            torch.manual_seed(0)
            cfg = preset(opts.preset, range=name)
            model = build_model(cfg).to(device)
            trainer = Trainer(
                model,
                OccupancyDataset(opts.data, opts.splits, cfg, max_scenarios=1),
                stage,
                opts.sample_fraction,
                1e-3,
                device,
            )
            rng = np.random.default_rng(0)
            trainer.step([0], [rng])  # warm-up (and, for fusion, the cached vehicle outputs)
            if gpu:
                torch.cuda.reset_peak_memory_stats(device)
            seconds, _ = timed(lambda: trainer.step([0], [rng]), opts.repeats)  # a step ends in .item(): synchronised
            memory = f", {torch.cuda.max_memory_allocated(device) / 2**30:.1f} GiB" if gpu else ""
            cells.append(f"{seconds:.3f}{memory}")
            print(f"{stage} {name}: {seconds:.3f} s/step{memory}", flush=True)
            if gpu:
                torch.cuda.empty_cache()
        rows.append(f"| {stage} | " + " | ".join(cells) + " |")
    where = torch.cuda.get_device_name(device) if gpu else f"{opts.threads} CPU threads"
    print(
        f"\nseconds per training step (median of {opts.repeats}){', peak GPU memory' if gpu else ''}, preset {opts.preset}, "
        f"{sum(p.numel() for p in build_model(preset(opts.preset)).parameters()):,} parameters, {where}\n"
    )
    print("\n".join(rows))


if __name__ == "__main__":
    main()
