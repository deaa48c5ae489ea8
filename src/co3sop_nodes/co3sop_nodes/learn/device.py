"""Where `train` and `evaluate` run: `--device auto | cpu | cuda | cuda:N` (ROS-free)."""

from __future__ import annotations

import argparse

import torch

from ..errors import Co3sopError


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="auto", help="torch device: auto (the first CUDA GPU if torch sees one, else cpu), cpu, cuda, cuda:N")


def select_device(name: str) -> torch.device:
    """The torch device `name` names, checked against what this torch build can use."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise Co3sopError(f"--device {name!r}: not a device (auto, cpu, cuda, cuda:N)") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise Co3sopError(f"--device {name!r}: only cpu and cuda are supported")
    count = torch.cuda.device_count()  # 0 on a CPU-only build or without a driver
    if count == 0:
        raise Co3sopError(f"--device {name}: this torch build ({torch.__version__}) sees no CUDA GPU")
    if device.index is not None and device.index >= count:
        raise Co3sopError(f"--device {name}: torch sees {count} CUDA GPU(s) (cuda:0..cuda:{count - 1})")
    return device
