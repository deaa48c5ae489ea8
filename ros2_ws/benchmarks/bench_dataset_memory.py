"""Resident memory of training and evaluation against the number of scenarios: flat, since samples stream.

    ros2_ws/benchmarks/bench_dataset_memory.py --data data/bench --split test --preset tiny-lidar --copies 10

The split's scenarios are linked (symbolic links, no copy) under new names into a dataset of `--copies` times
as many scenarios, beside the split itself. For each of the two, a fresh process indexes the dataset, trains
`--steps` steps (`train`'s Trainer and DataLoader, `--workers` reading ahead) and evaluates the same number of
samples, and reports its peak resident memory (ru_maxrss; the workers are processes of their own). The two
read the same number of samples, so only the dataset's size differs.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from co3sop_nodes.data import opv2v
from co3sop_nodes.eval.evaluate import evaluate
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.train.loader import StepSamples, step_loader
from co3sop_nodes.train.trainer import Trainer, sample_order, training_sample


def linked(data: Path, split: str, copies: int, out: Path) -> Path:
    """A dataset root whose `split` holds every scenario of data/split `copies` times, as symbolic links."""
    names = [n for s, n in opv2v.find_scenarios(data) if s == split]
    for folder in ["", *opv2v.LABEL_FOLDERS.values()]:
        if not (data / folder / split).is_dir():
            continue
        for copy in range(copies):
            for name in names:
                target = out / folder / split / f"{name}_{copy:03d}" if copy else out / folder / split / name
                target.parent.mkdir(parents=True, exist_ok=True)
                target.symlink_to((data / folder / split / name).resolve())
    return out


def child(opts) -> None:
    torch.set_num_threads(opts.threads)
    torch.manual_seed(0)
    cfg = preset(opts.preset)
    dataset = OccupancyDataset(opts.root, [opts.split], cfg)
    trainer = Trainer(build_model(cfg), "ego", 0.15, 1e-3)
    order = sample_order(len(dataset), 0, opts.steps)
    steps = StepSamples(dataset, order, 0, opts.steps, 1, 0, 1, training_sample(cfg, "ego"))
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for samples in step_loader(steps, opts.workers):
        trainer.step(samples, [rng])
    trained = time.perf_counter() - t0
    evaluate(trainer.model.eval(), dataset, indices=[int(i) for i in order], desc="evaluate")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        json.dumps(
            {
                "scenarios": len(dataset.scenarios),
                "frames": len(dataset.frames),
                "samples": len(dataset),
                "peak_rss_mb": peak,
                "train_s": trained,
            }
        )
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a dataset root written by `generate`")
    parser.add_argument("--split", default="test")
    parser.add_argument("--preset", default="tiny-lidar")
    parser.add_argument("--copies", type=int, default=10)
    parser.add_argument("--steps", type=int, default=40, help="training steps, and samples evaluated, in each run")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--root", type=Path, help=argparse.SUPPRESS)  # the child's dataset
    opts = parser.parse_args()
    if opts.root:
        child(opts)
        return 0
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for copies in (1, opts.copies):
            root = linked(opts.data, opts.split, copies, Path(tmp) / f"x{copies}")
            argv = [
                sys.executable,
                __file__,
                "--data",
                str(opts.data),
                "--split",
                opts.split,
                "--preset",
                opts.preset,
                "--steps",
                str(opts.steps),
                "--workers",
                str(opts.workers),
                "--threads",
                str(opts.threads),
                "--root",
                str(root),
            ]
            done = subprocess.run(argv, capture_output=True, text=True, check=False)
            if done.returncode:
                print(done.stderr, file=sys.stderr)
                return 1
            results.append(json.loads(done.stdout.strip().splitlines()[-1]))
            shutil.rmtree(root)
    small, large = results
    print(
        f"peak resident memory, {opts.preset}, {opts.steps} training steps ({opts.workers} workers) and evaluation "
        f"on {opts.data}/{opts.split} linked {opts.copies} times:\n"
    )
    print("| scenarios | frames | samples | peak RSS (MB) | training (s) |\n|---:|---:|---:|---:|---:|")
    for r in results:
        print(f"| {r['scenarios']} | {r['frames']} | {r['samples']} | {r['peak_rss_mb']:.0f} | {r['train_s']:.1f} |")
    print(f"\n{opts.copies}x the scenarios: peak RSS x {large['peak_rss_mb'] / small['peak_rss_mb']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
