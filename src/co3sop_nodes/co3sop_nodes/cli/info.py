"""`info`: summarise a bag, a folder of bags, a recording, or an OPV2V/Co3SOP dataset folder.

    ros2 run co3sop_nodes info PATH [--no-counts]

Prints scenarios, CAVs, frames, topics (bags and `recorder`'s MCAP files), and
per-class voxel counts of the ground truth per benchmark range.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.data.inventory import describe


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="info", description=__doc__.split("\n\n")[1])
    parser.add_argument("path", type=Path, help="a bag folder, a folder of bags, a recording (.mcap), or an OPV2V root")
    parser.add_argument("--no-counts", action="store_true", help="skip the per-class voxel counts (faster)")
    opts = parser.parse_args(args)
    print(describe(opts.path, not opts.no_counts))
    return 0


entry = run(main)
