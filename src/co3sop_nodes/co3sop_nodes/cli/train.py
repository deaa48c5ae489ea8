"""`train`: train Co3SOP-Base or a baseline on a generated (or converted) split.

    ros2 run co3sop_nodes train --data data/ --preset tiny --stage ego --steps 1500 --out runs/tiny-ego
    ros2 run co3sop_nodes train --data data/ --stage fusion --init runs/tiny-ego/model.pt --steps 800 --out runs/tiny

Stages as in Co3SOP: `ego` trains the vehicle half and the head on single
agents; `fusion` starts from an ego checkpoint, freezes the vehicle half and
trains the fusion and the head with collaborators; `joint` trains everything
at once. `wire` starts from a collaborative checkpoint and trains a code for
the V2X wire (K integers per voxel, --wire-rank) with the fusion and the head
behind it, each collaborator's voxels chosen by the ego's request as a byte
budget would (vehicle features frozen); vehicles send it with codec.learned.
Every CAV of every frame is the ego in turn. Progress bar, CSV log (log.csv),
loss plot (loss.png), resumable training state (state.pt, written atomically
every --save-every steps; --resume continues it) and the exported
model (model.pt, float16 weights + config + the command that made it).
`--device` picks CPU (the default without a GPU) or a CUDA GPU. `--batch B`
is the samples each process takes per step, as DistributedDataParallel users
expect: under `torchrun --nproc-per-node N` the same command trains
data-parallel on a global batch of N x B (printed at the start;
DistributedDataParallel averages the gradients, only rank 0 writes), and
gives the weights one process gets with `--batch` N x B.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.cli.device import add_device_argument
from co3sop_nodes.model.config import PRESETS
from co3sop_nodes.train.trainer import train


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="train", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data", type=Path, required=True, help="dataset root written by `generate` (or an OPV2V root)"
    )
    parser.add_argument("--splits", nargs="+", default=["train"], help="splits to train on")
    parser.add_argument(
        "--preset", default="tiny", choices=sorted(PRESETS), help="model preset (ignored with --init or --resume)"
    )
    parser.add_argument("--range", choices=["25.6m", "51.2m", "76.8m"], help="benchmark range (default: the preset's)")
    parser.add_argument("--stage", choices=("ego", "fusion", "joint", "wire"), default="joint")
    parser.add_argument("--wire-rank", type=int, default=4, help="wire stage: integers per voxel of a new wire code")
    parser.add_argument(
        "--wire-levels", type=int, default=7, help="wire stage: each integer in [-L, L] (int4 on the wire: L <= 7)"
    )
    parser.add_argument(
        "--init", type=Path, help="start from this checkpoint's weights (the ego stage's for --stage fusion)"
    )
    parser.add_argument("--steps", type=int, default=1000, help="optimisation steps (one global batch each)")
    parser.add_argument(
        "--batch",
        type=int,
        default=1,
        help="samples per step in each process; under torchrun the global batch is this times the processes",
    )
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument(
        "--schedule",
        choices=("constant", "cosine"),
        default="constant",
        help="learning rate over the run: constant, or cosine decay from --lr to 0 at --steps",
    )
    parser.add_argument(
        "--sample-fraction", type=float, default=0.15, help="share of full-resolution voxels in the loss per step"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--threads",
        type=int,
        help="CPU threads for torch (default 2; under torchrun the cores shared by its processes)",
    )
    add_device_argument(parser)
    parser.add_argument("--out", type=Path, required=True, help="run folder: state.pt, model.pt, log.csv, loss.png")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/state.pt")
    parser.add_argument("--save-every", type=int, default=200)
    parser.add_argument(
        "--workers",
        type=int,
        default=2,
        help="processes reading the next steps' samples while one trains (0: read in turn, in this process)",
    )
    parser.add_argument(
        "--cache",
        type=Path,
        help="folder for the preprocessed inputs (LiDAR occupancy, resized images) and labels: a later epoch or run "
        "reads them instead of decoding PNG and PCD again (keyed by the preset's sensor settings, range and files)",
    )
    opts = parser.parse_args(args)
    return train(opts, "train " + shlex.join(sys.argv[1:] if args is None else args))


entry = run(main)
