"""What neighbours can add: the share of ground-truth occupied voxels that the ego's LiDAR hits, and that the
ego's and its collaborators' LiDARs hit together (co3sop_nodes.eval.observed).

    ros2_ws/benchmarks/observed.py --data data/bench --splits test [--range 51.2m] [--out FILE.json]

Run with the workspace environment (`. ros2_ws/env.sh`). Every sample of the
split (every CAV the ego in turn, its collaborators as the benchmark chooses
them); shares over occupied ground truth (classes 1..23), per class and in
all. `report` adds the JSON written with --out beside the evaluation folders
to the results page.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from co3sop_nodes.eval.observed import observed, observed_table
from co3sop_nodes.model.config import preset
from co3sop_nodes.train.dataset import OccupancyDataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--splits", nargs="+", default=["test"])
    parser.add_argument("--range", default="51.2m")
    parser.add_argument("--out", type=Path, help="also write the result as JSON here")
    opts = parser.parse_args()
    dataset = OccupancyDataset(opts.data, opts.splits, preset("tiny-lidar", range=opts.range))
    result = observed(dataset)
    print(observed_table(result, f"{'+'.join(opts.splits)}, {opts.range}"))
    if opts.out:
        opts.out.parent.mkdir(parents=True, exist_ok=True)
        opts.out.write_text(json.dumps({"splits": opts.splits, "range": opts.range, **result}, indent=2) + "\n")


if __name__ == "__main__":
    main()
