"""`generate`: simulate train/validate/test splits of OPV2V-style scenarios with Co3SOP labels.

    ros2 run co3sop_nodes generate --out data/ --splits train=4 validate=1 test=1 --frames 20 --bags bags/
    ros2 run co3sop_nodes generate --recipe share/co3sop_nodes/config/benchmark.yaml --out data/bench

Each scenario is a procedural town with 2..7 CAVs (four cameras and a LiDAR each) and traffic, written in
the OPV2V folder layout with Co3SOP voxel labels for the three benchmark ranges, and optionally as a
rosbag2 bag; interrupted runs resume (co3sop_nodes.sim.generation).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.data import opv2v
from co3sop_nodes.data.bags import COMPRESS_HELP
from co3sop_nodes.sim.generation import REAL_SIZE, GenerateOptions, generate, read_recipe

DEFAULTS = GenerateOptions(out=Path())  # the library's defaults are the command's


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="generate", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--recipe",
        type=Path,
        help="a dataset recipe (YAML, e.g. config/benchmark.yaml): its values are the defaults; "
        "options given on the command line win",
    )
    parser.add_argument("--out", type=Path, required=True, help="dataset root (OPV2V layout)")
    parser.add_argument("--splits", nargs="+", default=DEFAULTS.splits, help="NAME=COUNT scenarios per split")
    parser.add_argument("--frames", type=int, default=DEFAULTS.frames, help="10 Hz frames per scenario")
    parser.add_argument(
        "--seed", type=int, default=DEFAULTS.seed, help="base seed: the same seed gives the same dataset"
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=DEFAULTS.workers,
        help="processes simulating scenarios in parallel; with fewer scenarios, each one's threads",
    )
    parser.add_argument(
        "--shard",
        default=DEFAULTS.shard,
        help="I/N: only the I-th of N disjoint shares of the scenarios (1 <= I <= N), so N "
        "machines generate one dataset; copy their OUT folders together",
    )
    parser.add_argument("--cavs", default=DEFAULTS.cavs, help="CAVs per scenario: N or MIN-MAX (OPV2V: 2-7)")
    parser.add_argument("--vehicles", type=int, default=DEFAULTS.vehicles, help="other moving vehicles per town")
    parser.add_argument(
        "--image-size",
        default=DEFAULTS.image_size,
        help="camera WIDTHxHEIGHT (OPV2V: 800x600); intrinsics scale with it",
    )
    parser.add_argument(
        "--lidar-steps", type=int, default=DEFAULTS.lidar_steps, help="LiDAR rays per channel per sweep"
    )
    parser.add_argument(
        "--label-margin",
        default=DEFAULTS.label_margin,
        metavar="SIDE,TOP",
        help="write label grids larger than each range's: SIDE voxels more on each side in x and y, TOP layers more "
        "on top (readers crop them back at the centre, as Co3SOP's LoadOccupancy does)",
    )
    parser.add_argument(
        "--real-size",
        action="store_true",
        help="the real dataset's sizes as defaults: 800x600 images, 2048 rays per LiDAR channel (64 channels), "
        "label grids with a margin of 8,4 (options given explicitly win)",
    )
    parser.add_argument("--extras", action="store_true", help="also write depth and semantic camera images")
    parser.add_argument("--bags", type=Path, help="also write one rosbag2 (MCAP) bag per scenario under this folder")
    parser.add_argument("--compress-bags", action="store_true", help=COMPRESS_HELP)
    parser.add_argument(
        "--pictures", action="store_true", help="write a BEV + cameras picture per CAV frame under OUT/pictures"
    )
    parser.add_argument("--picture-range", default=DEFAULTS.picture_range, choices=list(opv2v.LABEL_FOLDERS))
    known = parser.parse_known_args(args)[0]
    if known.real_size:
        parser.set_defaults(**REAL_SIZE)
    if known.recipe:
        parser.set_defaults(**read_recipe(known.recipe))
    opts = parser.parse_args(args)

    del opts.recipe, opts.real_size
    return generate(GenerateOptions(**vars(opts)))


entry = run(main)
