"""`evaluate`: per-class IoU and mIoU of a model on a split, and the paper's ablations.

    ros2 run co3sop_nodes evaluate --model runs/tiny/model.pt --data data/ --splits validate --out results/
    ros2 run co3sop_nodes evaluate ... --ablation collaborators   # 0..6 collaborators, nearest first
    ros2 run co3sop_nodes evaluate ... --ablation pose-noise      # mu in 0, 0.1, ..., 0.5, sigma 0.02
    ros2 run co3sop_nodes evaluate ... --ablation collaboration   # off vs on
    ros2 run co3sop_nodes evaluate ... --ablation codec           # bytes per agent-frame vs mIoU per feature codec
    ros2 run co3sop_nodes evaluate ... --ablation inputs          # real vs blank vs shuffled sensors (input controls)
    ros2 run co3sop_nodes evaluate ... --ablation distance        # off vs on by the nearest collaborator's distance
    ros2 run co3sop_nodes evaluate ... --precision bfloat16 --ablation precision   # against float32, labels compared
    ros2 run co3sop_nodes evaluate ... --precision int8 --ablation precision       # a calibrated LiDAR model's int8
    ros2 run co3sop_nodes evaluate ... --precision int8 --vehicle-precision bfloat16 --ablation precision
        # an ego node on int8 (its head) fusing the features of vehicle nodes on bfloat16
    ros2 run co3sop_nodes evaluate --model A.pt B.pt ... --collaborators 0   # every model alone (single agent)

Every CAV of every frame is the ego in turn. Results are printed as markdown
(per-class IoU in %, mIoU in the three conventions of co3sop_nodes.eval.metrics)
and written as <out>/<name>.md and .json; ablations also write a PNG plot.
Every mIoU carries a 95 % bootstrap interval over scenarios, and every
ablation step its paired difference to the step's reference (off, 0
collaborators, no noise, real inputs, the lossless codec) with its interval
(co3sop_nodes.eval.metrics.Bootstrap).
Pose noise follows Co3SOP: neighbours only, dx, dy ~ N(mu, sigma) (a biased
offset), dz ~ N(0, 0.01), applied to their world poses before alignment.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.cli.device import add_device_argument
from co3sop_nodes.eval.evaluate import ABLATIONS, evaluate_models
from co3sop_nodes.model.path import PRECISIONS


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="evaluate", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--model",
        nargs="+",
        help="checkpoints (model.pt or state.pt, or a shipped model by name: tiny-lidar, tiny, "
        "small); one column each (default: the shipped tiny-lidar)",
    )
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--splits", nargs="+", default=["validate"])
    parser.add_argument("--out", type=Path, default=Path("results"))
    parser.add_argument(
        "--ablation",
        nargs="*",
        default=[],
        choices=sorted(ABLATIONS),
        help="ablations to run for each model (they share the vehicle halves' outputs)",
    )
    parser.add_argument(
        "--collaborators",
        type=int,
        metavar="N",
        help="at most N collaborators, nearest first (0: every model alone; default: each model's maximum)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--cache",
        type=Path,
        help="folder for the preprocessed inputs and labels, shared with `train --cache` (see there)",
    )
    add_device_argument(parser)
    parser.add_argument(
        "--precision",
        default="float32",
        choices=PRECISIONS,
        help="inference precision (float32, the reference, by default; auto: what the machine computes fast)",
    )
    parser.add_argument(
        "--vehicle-precision",
        choices=PRECISIONS,
        help="the vehicle halves' precision, as vehicle nodes would run (default: --precision); --precision is then "
        "the ego's: its fusion and head",
    )
    parser.add_argument(
        "--reference-paths", action="store_true", help="the PyTorch reference paths instead of the compiled kernels"
    )
    opts = parser.parse_args(args)
    opts.command = shlex.join(["evaluate", *(sys.argv[1:] if args is None else args)])  # recorded beside every table
    if opts.collaborators is not None and opts.collaborators < 0:
        parser.error("--collaborators must be 0 or more")
    if opts.threads < 1:
        parser.error("--threads must be 1 or more")
    return evaluate_models(opts)


entry = run(main)
