"""`report`: the benchmark page (markdown) from `evaluate`'s JSON, so no figure is ever typed by hand.

    ros2 run co3sop_nodes report src/co3sop_nodes/doc/evaluation --out src/co3sop_nodes/doc/results.md \
        --goals src/co3sop_nodes/config/benchmark.yaml

RESULTS holds one folder per trained run, named <preset>-<range>-s<seed> (as
ros2_ws/run_protocol.sh writes them), each with the ablation JSON files of
`evaluate` on the test split. The page gives, per preset and range: the
commands that trained each seed, the collaboration gain of every seed with
its 95 % paired bootstrap interval over test scenarios, the mean and spread
over seeds, the input controls, and for the first seed the per-class table,
the number of collaborators, pose noise and the gain by the nearest
collaborator's distance; the number of collaborators and pose noise are also
set out across the three ranges, as the paper's figure and table do. Choices
made on `validate` (RESULTS/validate/<choice>/) close the page: fusion
recipes by their collaboration gain, and single-agent checkpoints scored alone
(one `evaluate` call with several --model), paired row by row.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.eval.report import write_report


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="report", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("results", type=Path, help="folder of <preset>-<range>-s<seed> evaluation folders")
    parser.add_argument("--out", type=Path, required=True, help="markdown page to write")
    parser.add_argument(
        "--goals",
        type=Path,
        metavar="RECIPE",
        help="a protocol recipe whose 'goals' section each model is set against (e.g. config/benchmark.yaml)",
    )
    opts = parser.parse_args(args)
    return write_report(opts.results, opts.out, opts.goals)


entry = run(main)
