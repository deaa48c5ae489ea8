"""ros2_ws/benchmarks/train_time.py: one timed piece per stretch of a run between resumes (ROS-free)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "ros2_ws" / "benchmarks" / "train_time.py"
spec = importlib.util.spec_from_file_location("train_time", SCRIPT)
train_time = importlib.util.module_from_spec(spec)
spec.loader.exec_module(train_time)


def test_a_resumed_run_is_timed_piece_by_piece(tmp_path):
    rows = [(s, 1.0 * s) for s in range(1, 5)] + [(s, 0.5 * (s - 2)) for s in range(3, 7)]  # resumed at step 2
    (tmp_path / "log.csv").write_text("step,stage,loss,seconds\n" + "".join(f"{s},ego,1.0,{t}\n" for s, t in rows))
    assert [[int(r["step"]) for r in p] for p in train_time.pieces(tmp_path / "log.csv")] == [[1, 2, 3, 4], [3, 4, 5, 6]]
    assert train_time.describe(tmp_path) == (f"{tmp_path}: steps 1-4 in 4 s (1.000 s/step); "
                                             "steps 3-6 in 2 s (0.500 s/step)")


def test_a_folder_without_a_log_is_named(tmp_path):
    with pytest.raises(SystemExit, match="log.csv: not a log.csv of train"):
        train_time.describe(tmp_path)
