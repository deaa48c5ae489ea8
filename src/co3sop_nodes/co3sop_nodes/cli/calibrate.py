"""`calibrate`: measure a LiDAR model's int8 activation ranges on a dataset split and write them into a checkpoint.

    ros2 run co3sop_nodes calibrate --model runs/x/model.pt --data data/bench --splits validate --out model.pt

With them, `precision int8` (the nodes' parameter, `evaluate`'s and `demo`'s option) computes the model's
SSCNet-style vehicle half and its head's layers up to 1/2 in int8 on the CPU. The ranges minimise each activation's
squared quantization error over every CAV's scan of the splits (the head's on each scan's own features:
inference/calibration.py); calibrate on train or validate, never on test.
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


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="calibrate", description=__doc__.split("\n\n")[1])
    parser.add_argument("--model", required=True, help="a checkpoint file, or a shipped model's name")
    parser.add_argument("--data", type=Path, required=True, help="an OPV2V / Co3SOP dataset root")
    parser.add_argument("--splits", nargs="+", default=["validate"], help="the splits whose scans are measured")
    parser.add_argument("--out", type=Path, required=True, help="the calibrated checkpoint (may be --model's file)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    opts = parser.parse_args(args)
    if "test" in opts.splits:
        parser.error("--splits test: the reported split is never used to choose anything; take train or validate")
    if opts.threads < 1:
        parser.error(f"--threads {opts.threads}: at least 1")
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
    save_calibrated(source, opts.out, ranges, made)
    for name, value in ranges.items():
        print(f"{name}: {value:.4g}")
    print(f"calibrate: {len(agents)} scans of {'+'.join(opts.splits)}; wrote {opts.out}")
    return 0


entry = run(main)
