"""A run's log.csv: one timed piece per stretch of a run between resumes (ROS-free)."""

from __future__ import annotations

import pytest

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.train.log import pieces, timing


def test_a_resumed_run_is_timed_piece_by_piece(tmp_path):
    rows = [(s, 1.0 * s) for s in range(1, 5)] + [(s, 0.5 * (s - 2)) for s in range(3, 7)]  # resumed at step 2
    (tmp_path / "log.csv").write_text("step,stage,loss,seconds\n" + "".join(f"{s},ego,1.0,{t}\n" for s, t in rows))
    assert [[int(r["step"]) for r in p] for p in pieces(tmp_path / "log.csv")] == [[1, 2, 3, 4], [3, 4, 5, 6]]
    assert timing(tmp_path) == (f"{tmp_path}: steps 1-4 in 4 s (1.000 s/step); steps 3-6 in 2 s (0.500 s/step)")


def test_a_folder_without_a_log_is_named(tmp_path):
    with pytest.raises(Co3sopError, match="log.csv: not a log.csv of train"):
        timing(tmp_path)
