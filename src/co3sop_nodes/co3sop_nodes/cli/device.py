"""The `--device auto | cpu | cuda | cuda:N` option of `train`, `evaluate` and the benchmarks (checked by
co3sop_nodes.model.path.resolve_device)."""

from __future__ import annotations

import argparse


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--device",
        default="auto",
        help="torch device: auto (the first CUDA GPU if torch sees one, else cpu), cpu, cuda, cuda:N",
    )
