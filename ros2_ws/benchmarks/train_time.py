"""How long training took: steps and seconds of each piece of a run, read from the `log.csv` that `train` writes.

    python3 ros2_ws/benchmarks/train_time.py RUN [RUN ...]

A run resumed with `--resume` (after an interruption, or on another machine)
starts its `seconds` column again, so each piece is timed on its own: its
first and last step, its seconds (data loading included) and seconds per step.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.train.log import timing


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (each with train's log.csv)")
    try:
        for run in parser.parse_args().runs:
            print(timing(run))
    except Co3sopError as exc:
        print(f"train_time: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
