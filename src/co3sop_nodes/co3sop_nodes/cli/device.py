"""Where `train` and `evaluate` run: `--device auto | cpu | cuda | cuda:N` (ROS-free)."""

from __future__ import annotations

import argparse

import torch

from co3sop_nodes.inference import resolve_device


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--device",
        default="auto",
        help="torch device: auto (the first CUDA GPU if torch sees one, else cpu), cpu, cuda, cuda:N",
    )


def select_device(name: str) -> torch.device:
    """The torch device `name` names, checked against what this torch build can use."""
    return resolve_device(name, "--device")
