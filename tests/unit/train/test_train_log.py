"""A run's log on resume: the steps an interrupted run logged past its last saved state are dropped
(ROS-free)."""

from __future__ import annotations

import csv

from co3sop_nodes.train.log import keep_log_until, log_header


def write_log(path, steps):
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["step", "stage", "loss", "seconds"])
        writer.writeheader()
        writer.writerows({"step": s, "stage": "fusion", "loss": 1.0 / s, "seconds": s * 0.5} for s in steps)
    return path.read_text()


def test_a_resume_drops_the_steps_logged_after_the_saved_state(tmp_path):
    log = tmp_path / "log.csv"
    text = write_log(log, range(1, 8))
    keep_log_until(log, 7)
    assert log.read_text() == text  # nothing past the state: the file is left as it is
    keep_log_until(log, 5)  # saved at 5, interrupted at 7
    rows = list(csv.DictReader(log.open()))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5] and float(rows[-1]["loss"]) == 1.0 / 5
    assert log.read_text() == "".join(text.splitlines(keepends=True)[:6])  # the same bytes, up to step 5
    assert [p.name for p in tmp_path.iterdir()] == ["log.csv"]  # no temporary file left


def test_a_run_without_a_log_has_nothing_to_drop(tmp_path):
    keep_log_until(tmp_path / "log.csv", 3)
    assert not (tmp_path / "log.csv").exists()


def test_a_resumed_run_writes_under_the_logs_own_columns(tmp_path):
    log = tmp_path / "log.csv"
    assert log_header(log) is None  # a new run: its first row names the columns
    write_log(log, range(1, 3))
    assert log_header(log) == ["step", "stage", "loss", "seconds"]
