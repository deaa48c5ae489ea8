"""`calibrate`: measure a LiDAR model's int8 activation ranges on a dataset split and write them into a checkpoint.

    ros2 run co3sop_nodes calibrate --model runs/x/model.pt --data data/bench --splits validate --out model.pt
    ros2 run co3sop_nodes calibrate --model M.pt --data data/bench --splits validate --fine-tune train --out M.pt

With them, `precision int8` (the nodes' parameter, `evaluate`'s and `demo`'s option) computes the model's
SSCNet-style vehicle half and its head's layers up to 1/2 in int8 on the CPU. The ranges minimise each activation's
squared quantization error over every CAV's scan of the splits (the head's on each scan's own features:
inference/calibration.py); calibrate on train or validate, never on test. With --fine-tune, the vehicle half's int8
layers then get weights of their own, fine-tuned through the int8 arithmetic on those splits' scans toward the float
layers' features (train/quantization_aware.py; resumable: run the same command again after an interruption).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import torch

from co3sop_nodes.cli.common import run
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.common.progress import progress
from co3sop_nodes.inference.calibration import calibrate
from co3sop_nodes.inference.checkpoint import load_model, resolve_checkpoint, save_calibrated
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.train.quantization_aware import fine_tune_int8


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="calibrate", description=__doc__.split("\n\n")[1])
    parser.add_argument("--model", required=True, help="a checkpoint file, or a shipped model's name")
    parser.add_argument("--data", type=Path, required=True, help="an OPV2V / Co3SOP dataset root")
    parser.add_argument("--splits", nargs="+", default=["validate"], help="the splits whose scans are measured")
    parser.add_argument("--out", type=Path, required=True, help="the calibrated checkpoint (may be --model's file)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument(
        "--fine-tune", nargs="+", default=[], metavar="SPLIT", help="fine-tune the vehicle half's int8 layers on these"
    )
    parser.add_argument("--steps", type=int, default=1500, help="fine-tuning steps (one scan each)")
    parser.add_argument("--lr", type=float, default=1e-4, help="fine-tuning learning rate (Adam)")
    parser.add_argument("--seed", type=int, default=0, help="fine-tuning: the order of the scans")
    opts = parser.parse_args(args)
    for flag, splits in (("--splits", opts.splits), ("--fine-tune", opts.fine_tune)):
        if "test" in splits:
            parser.error(f"{flag} test: the reported split is never used to choose anything; take train or validate")
    if opts.threads < 1:
        parser.error(f"--threads {opts.threads}: at least 1")
    if opts.steps < 1 or not opts.lr > 0:
        parser.error(f"--steps {opts.steps} --lr {opts.lr}: at least one step, a positive rate")
    torch.set_num_threads(opts.threads)
    source = resolve_checkpoint(opts.model, "--model")
    model, _ = load_model(source)
    if model.cfg.modality != "lidar" or not model.int8_activations():
        raise Co3sopError(
            f"--model {opts.model}: {model.cfg.name} is not a LiDAR model with int8 layers (calibrate measures on "
            "scans: an SSCNet-style vehicle half, a convolutional head)"
        )
    dataset = OccupancyDataset(opts.data, opts.splits, model.cfg)
    agents = [(f, j) for f, frame in enumerate(dataset.frames) for j in range(len(frame.cavs))]
    bar = progress(len(agents), "calibrate", "scan")

    def scans():
        for f, j in agents:
            yield torch.from_numpy(dataset.agent(f, j).inputs["occupancy"])[None]
            bar.update(1)

    ranges = calibrate(model, scans())
    bar.close()
    command = shlex.join(["calibrate", *(sys.argv[1:] if args is None else args)])
    made = {"command": command, "data": str(opts.data), "splits": list(opts.splits), "scans": len(agents)}
    weights = {}
    if opts.fine_tune:
        weights = fine_tune(model.calibrate(ranges), opts)
        made["fine_tune"] = {"splits": list(opts.fine_tune), "steps": opts.steps, "lr": opts.lr, "seed": opts.seed}
    save_calibrated(source, opts.out, ranges, made, weights)
    for name, value in ranges.items():
        print(f"{name}: {value:.4g}")
    tuned = f"; the int8 layers fine-tuned on {'+'.join(opts.fine_tune)} ({opts.steps} steps)" if weights else ""
    print(f"calibrate: {len(agents)} scans of {'+'.join(opts.splits)}{tuned}; wrote {opts.out}")
    return 0


def fine_tune(model, opts) -> dict[str, torch.Tensor]:
    """The vehicle half's int8 layers fine-tuned on --fine-tune's scans (resumable from a state beside --out)."""
    if "vehicle.encoder" not in model.int8_modules:
        raise Co3sopError(f"--fine-tune: {model.cfg.name} has no SSCNet-style vehicle half with int8 layers")
    dataset = OccupancyDataset(opts.data, opts.fine_tune, model.cfg)
    agents = [(f, j) for f, frame in enumerate(dataset.frames) for j in range(len(frame.cavs))]

    def scan(i: int) -> torch.Tensor:
        return torch.from_numpy(dataset.agent(*agents[i]).inputs["occupancy"])[None]

    bar = progress(opts.steps, "fine-tune int8", "step")
    state = opts.out.with_name(opts.out.name + ".int8-tuning")

    def on_step(step: int, loss: float) -> None:
        bar.set_postfix(loss=f"{loss:.4g}", refresh=False)
        bar.update(step + 1 - bar.n)  # a resumed run starts past 0

    weights = fine_tune_int8(model, scan, len(agents), opts.steps, opts.lr, opts.seed, state, on_step)
    bar.close()
    return weights


entry = run(main)
