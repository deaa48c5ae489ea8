"""`convert`: OPV2V folders (with Co3SOP labels when present) -> rosbag2 bags that replay like ours.

    ros2 run co3sop_nodes convert OPV2V_ROOT --out bags/ [--on-error stop|skip] [--splits test]

One bag per scenario (<out>/<split>/<scenario>/), REP-103 frames and the same
topics as the simulator's bags. With --on-error stop (default) a scenario is
read and checked completely before anything is written, and the first bad
file stops the run with an error naming it; with --on-error skip, unreadable
timestamps are left out and reported.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.common.progress import progress
from co3sop_nodes.data import opv2v
from co3sop_nodes.data.bags import COMPRESS_HELP, BagWriter


def convert_scenario(
    root: Path, split: str, scenario: str, bag: Path, on_error: str, ranges, compress: bool = False
) -> list[str]:
    """Writes one scenario's bag; returns the problems skipped (on_error="skip")."""
    problems = []
    if on_error == "stop":  # check everything before writing anything
        for _, frames in opv2v.read_scenario(root, split, scenario, ranges):
            if isinstance(frames, DatasetError):
                raise frames
    with BagWriter(bag, compress=compress) as writer:
        for ts, frames in opv2v.read_scenario(root, split, scenario, ranges):
            if isinstance(frames, DatasetError):
                problems.append(f"{split}/{scenario} timestamp {ts:06d} skipped: {frames}")
                continue
            writer.write(frames)
        if not writer.messages:
            raise DatasetError(f"{root / split / scenario}: no readable timestamp")
    return problems


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="convert", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("root", type=Path, help="OPV2V root holding train/ validate/ test/ (and additional_*/ labels)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the bags")
    parser.add_argument(
        "--on-error",
        choices=("stop", "skip"),
        default="stop",
        help="bad file: stop before writing, or skip that timestamp",
    )
    parser.add_argument("--splits", nargs="*", default=list(opv2v.SPLITS), help="splits to convert")
    parser.add_argument(
        "--ranges",
        nargs="*",
        default=list(BENCHMARK_RANGES),
        choices=list(BENCHMARK_RANGES),
        help="label ranges to include",
    )
    parser.add_argument("--compress", action="store_true", help=COMPRESS_HELP)
    opts = parser.parse_args(args)
    scenarios = [(s, n) for s, n in opv2v.find_scenarios(opts.root) if s in opts.splits]
    problems = []
    bar = progress(len(scenarios), "scenarios", "scenario")
    for split, name in scenarios:
        problems += convert_scenario(
            opts.root, split, name, opts.out / split / name, opts.on_error, opts.ranges, opts.compress
        )
        bar.update(1)
    bar.close()
    for p in problems:
        print(f"convert: {p}")
    print(f"convert: {len(scenarios)} bag(s) in {opts.out}; {len(problems)} timestamp(s) skipped")
    return 0


entry = run(main)
