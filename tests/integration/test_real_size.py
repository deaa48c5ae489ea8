"""A scenario at the real dataset's sizes (800x600 images, 64-channel LiDAR at 2048 rays per channel, label grids
larger than the ranges', as Co3SOP's may be) through the tools a user runs on the real data: generate, convert,
info, train (streamed samples, the cache, DataLoader workers) and evaluate."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_dataset_tools import tool

from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.data import opv2v


@pytest.fixture(scope="module")
def real_size(tmp_path_factory):
    root = tmp_path_factory.mktemp("real")
    done = tool(
        "generate",
        "--real-size",
        "--out",
        str(root / "data"),
        "--splits",
        "train=1",
        "--frames",
        "2",
        "--cavs",
        "2",
        "--vehicles",
        "4",
        "--workers",
        "1",
    )
    assert done.returncode == 0, done.stderr
    return root


def test_real_size_scenarios_have_the_real_shapes(real_size):
    data = real_size / "data"
    ((split, name),) = opv2v.find_scenarios(data)
    cavs, timestamps = opv2v.scenario_timestamps(data / split / name)
    frame = opv2v.read_cav_frame(data, split, name, cavs[0], timestamps[0], ("51.2m",))
    assert all(c.rgb.shape == (600, 800, 3) for c in frame.cameras)
    assert len(frame.points) > 20_000  # 64 channels x 2048 rays, the sky's left out
    raw = np.load(opv2v.label_path(data, "51.2m", split, name, int(cavs[0]), timestamps[0]))["voxels"]
    assert raw.shape == (272, 272, 28) and frame.labels["51.2m"].shape == BENCHMARK_RANGES["51.2m"].dims


def test_real_size_data_goes_through_convert_info_train_and_evaluate(real_size, tmp_path):
    data, bags = real_size / "data", tmp_path / "bags"
    done = tool("convert", str(data), "--out", str(bags))
    assert done.returncode == 0, done.stderr
    done = tool("info", str(bags))
    assert done.returncode == 0, done.stderr
    assert "; 2 frames" in done.stdout and "| 7 road |" in done.stdout, done.stdout  # per-class counts, cropped labels
    done = tool("info", str(data))
    assert done.returncode == 0 and "1 scenario(s): train 1" in done.stdout, done.stderr
    run = tmp_path / "run"
    cache = tmp_path / "cache"
    for resume in (False, True):  # the second run reads every sample from the cache the first one filled
        done = tool(
            "train",
            "--data",
            str(data),
            "--preset",
            "tiny-lidar",
            "--stage",
            "joint",
            "--steps",
            "3" if resume else "2",
            "--workers",
            "2",
            "--cache",
            str(cache),
            "--out",
            str(run),
            *(["--resume"] if resume else []),
        )
        assert done.returncode == 0, done.stderr
        assert "waiting for data (2 workers)" in done.stdout
    assert any(cache.rglob("*.npz"))
    done = tool(
        "evaluate",
        "--model",
        str(run / "model.pt"),
        "--data",
        str(data),
        "--splits",
        "train",
        "--cache",
        str(cache),
        "--out",
        str(tmp_path / "eval"),
    )
    assert done.returncode == 0, done.stderr
    table = json.loads((tmp_path / "eval" / "evaluation.json").read_text())
    assert next(v for k, v in table.items() if k.startswith("tiny-lidar"))["frames"] == 4  # 2 frames x 2 egos
