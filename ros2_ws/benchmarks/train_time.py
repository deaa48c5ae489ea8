"""How long training took: steps and seconds of each piece of a run, read from the `log.csv` that `train` writes.

    python3 ros2_ws/benchmarks/train_time.py RUN [RUN ...]

A run resumed with `--resume` (after an interruption, or on another machine)
starts its `seconds` column again, so each piece is timed on its own: its
first and last step, its seconds (data loading included) and seconds per step.
Needs only the standard library.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path


def pieces(log: Path) -> list[list[dict]]:
    """The rows of a run's log.csv split where `seconds` starts again (a resume)."""
    out: list[list[dict]] = []
    with log.open(newline="") as f:
        for row in csv.DictReader(f):
            if not out or float(row["seconds"]) < float(out[-1][-1]["seconds"]):
                out.append([])
            out[-1].append(row)
    return out


def describe(run: Path) -> str:
    log = run / "log.csv"
    try:
        parts = pieces(log)
    except (OSError, KeyError, ValueError) as exc:
        raise SystemExit(f"train_time: {log}: not a log.csv of train ({exc})") from None
    return f"{run}: " + "; ".join(
        f"steps {p[0]['step']}-{p[-1]['step']} in {float(p[-1]['seconds']):.0f} s ({float(p[-1]['seconds']) / len(p):.3f} s/step)"
        for p in parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (each with train's log.csv)")
    for run in parser.parse_args().runs:
        print(describe(run))


if __name__ == "__main__":
    sys.exit(main())
