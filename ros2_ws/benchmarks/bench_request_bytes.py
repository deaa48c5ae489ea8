"""Request maps on the wire: bytes of an ego's RequestMap message and the ego's time to encode it, per request_levels
and zstd level, over a split's frames.

    ros2_ws/benchmarks/bench_request_bytes.py --data data/bench [--splits validate] [--model tiny-lidar]
        [--levels 2 4 8 16 256] [--zstd 3 9 15 19] [--frames 40] [--out FILE.json]

Run with the workspace environment (`. ros2_ws/env.sh`). Each frame's map is the ego's own (1 - its confidence, as
the ego node makes it), from `--frames` frames spread evenly over the split, first agent of each; bytes are the
serialized ROS message (CDR: header, pose, grid and the compressed need). Prints a markdown table: mean, 95th
percentile and largest bytes, and the median ms to encode. bench_shared_channel.py's REQUEST_BYTES come from here.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch
from rclpy.serialization import serialize_message

from co3sop_nodes.common.geometry import Pose
from co3sop_nodes.inference.checkpoint import DEFAULT_MODEL, load_model, resolve_checkpoint
from co3sop_nodes.inference.inputs import to_batch
from co3sop_nodes.messages import request_msg
from co3sop_nodes.ros.message_types import RCLPY
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.v2x.codec import REQUEST_ZSTD_LEVEL, encode_request
from co3sop_nodes.v2x.request_map import request_of


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--splits", nargs="+", default=["validate"])
    parser.add_argument("--model", default=DEFAULT_MODEL, help="shipped model name or checkpoint path")
    parser.add_argument("--levels", type=int, nargs="+", default=[2, 4, 8, 16, 256])
    parser.add_argument("--zstd", type=int, nargs="+", default=sorted({3, 9, REQUEST_ZSTD_LEVEL, 19}))
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--out", type=Path, help="also write the table as JSON here")
    opts = parser.parse_args()
    torch.set_num_threads(1)
    path = Path(os.path.relpath(resolve_checkpoint(opts.model)))
    model, _ = load_model(path)
    dataset = OccupancyDataset(opts.data, opts.splits, model.cfg)
    grid = model.cfg.feature_grid
    step = max(1, len(dataset.frames) // opts.frames)
    needs = []  # (map (X, Y, Z) in [0, 1], world_from_lidar)
    with torch.no_grad():
        for f in range(0, len(dataset.frames), step)[: opts.frames]:
            agent = dataset.agent(f, 0)
            needs.append(
                (request_of(model.vehicle(**to_batch(agent.inputs, "cpu")).confidence), agent.world_from_lidar)
            )
    rows = []
    for levels in opts.levels:
        for zstd in opts.zstd:
            sizes, ms = [], []
            for need, pose in needs:
                t0 = time.perf_counter()
                enc = encode_request(need, grid, levels=levels, level=zstd)
                ms.append(1e3 * (time.perf_counter() - t0))
                msg = request_msg(
                    RCLPY, enc, stamp_ns=0, frame_id="cav_0/lidar", agent_id=0, pose=Pose.from_matrix(pose)
                )
                sizes.append(len(serialize_message(msg)))
            rows.append(
                {
                    "levels": levels,
                    "zstd": zstd,
                    "mean": float(np.mean(sizes)),
                    "p95": float(np.percentile(sizes, 95)),
                    "max": max(sizes),
                    "encode_ms": float(np.median(ms)),
                }
            )
    print(
        f"{model.cfg.name} {model.cfg.range} ({path}), {'+'.join(opts.splits)}: {len(needs)} frames, feature grid "
        f"{'x'.join(map(str, grid.dims))}; RequestMap bytes serialized\n"
    )
    print("| levels | zstd | mean B | p95 B | max B | encode ms |\n|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        mark = " (default)" if r["zstd"] == REQUEST_ZSTD_LEVEL else ""
        print(
            f"| {r['levels']} | {r['zstd']}{mark} | {r['mean']:,.0f} | {r['p95']:,.0f} | {r['max']:,} | "
            f"{r['encode_ms']:.1f} |"
        )
    if opts.out:
        opts.out.parent.mkdir(parents=True, exist_ok=True)
        opts.out.write_text(json.dumps({"model": str(path), "splits": opts.splits, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
