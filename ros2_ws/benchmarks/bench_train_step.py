"""Training benchmark: seconds per optimisation step of each stage at each range, on real samples; with
--pipeline, the data pipeline's throughput against the training step's.

    ros2_ws/benchmarks/bench_train_step.py --data data/tiny [--preset tiny] [--repeats 5] [--stages ego fusion]
        [--ranges 51.2m] [--device cuda]
    ros2_ws/benchmarks/bench_train_step.py --pipeline --data data/bench --splits train --presets tiny-lidar tiny small
        [--steps 30] [--workers 2] [--cache /tmp/co3sop-cache]

--pipeline: per preset, `train`'s joint stage for --steps steps of one sample (an ego with its collaborators),
fed by its DataLoader with --workers processes reading ahead. It reports the samples per second the
pipeline delivers alone (decoding PNG / PCD and labels; and from the cache, when --cache is given and the
first pass filled it), the time of the first training step (the workers starting, on a GPU its kernels
loading), and over the steady steps after it the samples per second training takes and the share of
training time spent waiting for data.

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
import time
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
from co3sop_nodes.train.loader import StepSamples, step_loader
from co3sop_nodes.train.trainer import Trainer, sample_order, training_sample


def pipeline(opts, device) -> None:
    gpu = device.type == "cuda"
    rows = [
        "| preset | pipeline, decoding (samples/s) | pipeline, cached (samples/s) | first step (s) "
        "| training (samples/s) | waiting for data |" + (" peak GPU memory (GiB) |" if gpu else ""),
        "|---|---:|---:|---:|---:|---:|" + ("---:|" if gpu else ""),
    ]
    for name in opts.presets:
        torch.manual_seed(0)
        cfg = preset(name)
        dataset = OccupancyDataset(opts.data, opts.splits, cfg, cache=opts.cache)
        order = sample_order(len(dataset), 0, opts.steps)
        steps = StepSamples(dataset, order, 0, opts.steps, 1, 0, 1, training_sample(cfg, "joint"))

        def delivered() -> float:
            t0 = time.perf_counter()
            for samples in step_loader(steps, opts.workers, device):
                if isinstance(samples, Exception):
                    raise samples
            return opts.steps / (time.perf_counter() - t0)

        decoding = delivered()
        cached = delivered() if opts.cache else None
        trainer = Trainer(build_model(cfg).to(device), "joint", opts.sample_fraction, 1e-3, device)
        rng, waited = np.random.default_rng(0), 0.0
        if gpu:
            torch.cuda.reset_peak_memory_stats(device)
        t0 = time.perf_counter()
        loaded = iter(step_loader(steps, opts.workers, device))
        # the first step (workers starting; on a GPU, its kernels loading) is timed apart from the steady steps
        trainer.step(next(loaded), [rng])
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(opts.steps - 1):
            t_wait = time.perf_counter()
            samples = next(loaded)
            waited += time.perf_counter() - t_wait
            trainer.step(samples, [rng])
        total = time.perf_counter() - t0
        row = (
            f"| {name} | {decoding:.2f} | {f'{cached:.2f}' if cached else '-'} | {first:.2f} "
            f"| {(opts.steps - 1) / total:.2f} | {100 * waited / total:.1f} % |"
        ) + (f" {torch.cuda.max_memory_allocated(device) / 2**30:.1f} |" if gpu else "")
        print(row, flush=True)
        rows.append(row)
    print(
        f"\n{opts.steps} joint-stage steps of one sample each per preset (the first timed apart) on {opts.data} "
        f"({'+'.join(opts.splits)}), "
        f"{opts.workers} DataLoader workers, {opts.threads} torch threads, {device}:\n"
    )
    print("\n".join(rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pipeline", action="store_true", help="the data pipeline against the training step")
    parser.add_argument("--presets", nargs="+", default=["tiny-lidar", "tiny", "small"])
    parser.add_argument("--steps", type=int, default=30, help="--pipeline: steps per preset")
    parser.add_argument("--workers", type=int, default=2, help="--pipeline: DataLoader workers")
    parser.add_argument("--cache", type=Path, help="--pipeline: the preprocessed-input cache folder")
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
    if opts.pipeline:
        if opts.steps < 2:
            parser.error(f"--steps {opts.steps}: --pipeline times a first step apart from at least one more")
        return pipeline(opts, device)
    gpu = device.type == "cuda"
    rows = ["| stage | " + " | ".join(opts.ranges) + " |", "|---|" + "---:|" * len(opts.ranges)]
    for stage in opts.stages:
        cells = []
        for name in opts.ranges:
            torch.manual_seed(0)
            cfg = preset(opts.preset, range=name)
            model = build_model(cfg).to(device)
            trainer = Trainer(model, stage, opts.sample_fraction, 1e-3, device)
            sample = training_sample(cfg, stage)(OccupancyDataset(opts.data, opts.splits, cfg, max_scenarios=1), 0)
            rng = np.random.default_rng(0)
            trainer.step([sample], [rng])  # warm-up (and, for fusion, the cached vehicle outputs)
            if gpu:
                torch.cuda.reset_peak_memory_stats(device)
            seconds, _ = timed(lambda: trainer.step([sample], [rng]), opts.repeats)  # ends in .item(): synchronised
            memory = f", {torch.cuda.max_memory_allocated(device) / 2**30:.1f} GiB" if gpu else ""
            cells.append(f"{seconds:.3f}{memory}")
            print(f"{stage} {name}: {seconds:.3f} s/step{memory}", flush=True)
            if gpu:
                torch.cuda.empty_cache()
        rows.append(f"| {stage} | " + " | ".join(cells) + " |")
    where = torch.cuda.get_device_name(device) if gpu else f"{opts.threads} CPU threads"
    print(
        f"\nseconds per training step (median of {opts.repeats}){', peak GPU memory' if gpu else ''}, preset "
        f"{opts.preset}, "
        f"{sum(p.numel() for p in build_model(preset(opts.preset)).parameters()):,} parameters, {where}\n"
    )
    print("\n".join(rows))


if __name__ == "__main__":
    main()
