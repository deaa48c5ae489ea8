"""Scans on the wire: bytes of a vehicle's VoxelScan message (send:=scan) and its time to encode it, per zstd level,
over every agent of every frame of a split.

    ros2_ws/benchmarks/bench_scan_bytes.py --data data/bench [--splits test] [--model tiny-lidar]
        [--zstd 3 9 15 19] [--out FILE.json]

Run with the workspace environment (`. ros2_ws/env.sh`). Each scan is the agent's LiDAR occupancy on the model's
grid (the input of its vehicle half), whole (no budget); bytes are the serialized ROS message (CDR: header, pose,
grid and the compressed occupancy). Prints a markdown table: occupied voxels (median), the message's median, 95th
percentile and largest bytes, the share of scans over 7,950 bytes, and the median ms to encode.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from rclpy.serialization import serialize_message

from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.inference.checkpoint import DEFAULT_MODEL, load_model, resolve_checkpoint
from co3sop_nodes.messages import scan_msg
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.v2x.scan import ScanCodecConfig, encode_scan

BUDGET = 7950  # bytes: the goal's 8 KB a neighbour-frame, as bench_learned_codec's budgets count them


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--splits", nargs="+", default=["test"])
    parser.add_argument("--model", default=DEFAULT_MODEL, help="a LiDAR model: shipped name or checkpoint path")
    parser.add_argument("--zstd", type=int, nargs="+", default=[3, 9, 15, 19], help="zstd levels (codec.level)")
    parser.add_argument("--out", type=Path, help="also write the rows as JSON here")
    opts = parser.parse_args()
    model, _ = load_model(resolve_checkpoint(opts.model, "--model"))
    if model.cfg.modality != "lidar":
        parser.error(f"--model {opts.model}: a {model.cfg.modality} model takes no scan")
    dataset = OccupancyDataset(opts.data, opts.splits, model.cfg)
    grid = model.cfg.grid
    scans = [
        dataset.agent(f, j).inputs["occupancy"][0]
        for f, frame in enumerate(dataset.frames)
        for j in range(len(frame.cavs))
    ]
    rows = []
    for level in opts.zstd:
        sizes, times = [], []
        for occupancy in scans:
            t0 = time.perf_counter()
            enc = encode_scan(occupancy, grid, ScanCodecConfig(level=level))
            times.append(time.perf_counter() - t0)
            msg = scan_msg(RCLPY, enc, stamp_ns=0, frame_id="cav_1/lidar", agent_id=1, pose=Pose((0.0, 0.0, 0.0)))
            sizes.append(len(serialize_message(msg)))
        sizes = np.array(sizes)
        rows.append(
            {
                "zstd": level,
                "scans": len(sizes),
                "occupied": int(np.median([int(np.count_nonzero(o)) for o in scans])),
                "median": int(np.median(sizes)),
                "p95": int(np.percentile(sizes, 95)),
                "max": int(sizes.max()),
                "over_budget": float(np.mean(sizes > BUDGET)),
                "encode_ms": 1e3 * float(np.median(times)),
            }
        )
    print(
        f"{model.cfg.name} {model.cfg.range} ({'x'.join(map(str, grid.dims))} @ {grid.voxel_size:g} m), "
        f"{opts.data} {'+'.join(opts.splits)}: every agent's scan, whole\n"
    )
    print(
        "| zstd level | scans | occupied voxels (median) | bytes: median | p95 | largest | over 7,950 B | encode ms |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['zstd']} | {r['scans']} | {r['occupied']:,} | {r['median']:,} | {r['p95']:,} | {r['max']:,} | "
            f"{100 * r['over_budget']:.0f} % | {r['encode_ms']:.1f} |"
        )
    if opts.out:
        opts.out.parent.mkdir(parents=True, exist_ok=True)
        opts.out.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
