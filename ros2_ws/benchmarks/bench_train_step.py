"""Training benchmark: seconds per optimisation step of each stage at each range, on real samples.

    ros2_ws/benchmarks/bench_train_step.py --data data/tiny [--preset tiny] [--repeats 5] [--stages ego fusion]

Run with the workspace environment (`. ros2_ws/env.sh`) on a split written by
`generate`. Each stage at each benchmark range trains a fresh model (untrained
weights: timing does not depend on them) on the split's first sample (an ego
with all its collaborators) for one warm-up step and then `--repeats` steps,
with `train`'s Trainer and sample fraction; the fusion stage caches the frozen
vehicle outputs after their first use, as `train` does, so its figure is the
steady fusion + head step. To compare
two versions of the code, run the script with each on PYTHONPATH (e.g. a
`git worktree` of the older commit) back to back on the same machine.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from co3sop_nodes.grid import BENCHMARK_RANGES
from co3sop_nodes.learn.dataset import OccupancyDataset
from co3sop_nodes.learn.train import Trainer
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.model import build_model
from timing import timed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--splits", nargs="+", default=["train"])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--stages", nargs="+", default=["ego", "fusion"], choices=["ego", "fusion", "joint"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sample-fraction", type=float, default=0.15)
    parser.add_argument("--threads", type=int, default=2)
    opts = parser.parse_args()
    torch.set_num_threads(opts.threads)
    rows = ["| stage | " + " | ".join(BENCHMARK_RANGES) + " |", "|---|" + "---:|" * len(BENCHMARK_RANGES)]
    for stage in opts.stages:
        cells = []
        for name in BENCHMARK_RANGES:
            torch.manual_seed(0)
            cfg = preset(opts.preset, range=name)
            trainer = Trainer(build_model(cfg), OccupancyDataset(opts.data, opts.splits, cfg), stage, opts.sample_fraction, 1e-3)
            rng = np.random.default_rng(0)
            trainer.step([0], [rng])  # warm-up (and, for fusion, the cached vehicle outputs)
            seconds, _ = timed(lambda: trainer.step([0], [rng]), opts.repeats)
            cells.append(f"{seconds:.2f}")
            print(f"{stage} {name}: {seconds:.2f} s/step", flush=True)
        rows.append(f"| {stage} | " + " | ".join(cells) + " |")
    print(f"\nseconds per training step (median of {opts.repeats}), preset {opts.preset}, {opts.threads} threads\n")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
