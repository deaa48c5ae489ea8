"""A training run's log.csv: one row per step (losses, learning rate, seconds since the run or its resume
started), kept consistent across resumes, plotted, and timed piece by piece."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from co3sop_nodes.common.errors import Co3sopError


def keep_log_until(csv_path: Path, step: int) -> None:
    """Drop the rows after `step` from a run's log: an interrupted run logged steps past its last saved state,
    which its resume trains again (the log then shows each step once, as the weights saw it)."""
    if not csv_path.is_file():
        return
    with open(csv_path, newline="") as f:
        lines = f.read().splitlines(keepends=True)
    kept = lines[:1] + [line for row, line in zip(csv.DictReader(lines), lines[1:]) if int(row["step"]) <= step]
    if len(kept) < len(lines):
        tmp = csv_path.with_name(f".{csv_path.name}.tmp")
        tmp.write_text("".join(kept))
        tmp.replace(csv_path)  # atomic: an interruption leaves the whole log


def log_header(csv_path: Path) -> list[str] | None:
    """The columns of a run's log.csv, None where it has none yet: a resumed run writes its rows under them."""
    if not csv_path.is_file():
        return None
    with open(csv_path, newline="") as f:
        return next(csv.reader(f), None)


def plot_losses(csv_path: Path, png_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(csv_path) as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return
    steps = np.array([int(r["step"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(steps, loss, lw=0.6, alpha=0.4, label="loss")
    window = max(1, len(loss) // 30)
    ax.plot(
        steps[window - 1 :], np.convolve(loss, np.ones(window) / window, mode="valid"), lw=2, label=f"mean of {window}"
    )
    for stage in sorted({r["stage"] for r in rows}):
        first = next(int(r["step"]) for r in rows if r["stage"] == stage)
        ax.axvline(first, color="grey", ls=":")
        ax.text(first, ax.get_ylim()[1], f" {stage}", va="top", fontsize=8)
    ax.set_xlabel("step")
    ax.set_ylabel("total loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)


def pieces(log: Path) -> list[list[dict]]:
    """The rows of a run's log.csv split where `seconds` starts again (a resume)."""
    out: list[list[dict]] = []
    with log.open(newline="") as f:
        for row in csv.DictReader(f):
            if not out or float(row["seconds"]) < float(out[-1][-1]["seconds"]):
                out.append([])
            out[-1].append(row)
    return out


def timing(run: Path) -> str:
    """Steps and seconds of each piece of a run (a run resumed with --resume starts its `seconds` again, so each
    piece is timed on its own, data loading included)."""
    log = run / "log.csv"
    try:
        parts = pieces(log)
    except (OSError, KeyError, ValueError) as exc:
        raise Co3sopError(f"{log}: not a log.csv of train ({exc})") from None
    return f"{run}: " + "; ".join(
        f"steps {p[0]['step']}-{p[-1]['step']} in {float(p[-1]['seconds']):.0f} s "
        f"({float(p[-1]['seconds']) / len(p):.3f} s/step)"
        for p in parts
    )
