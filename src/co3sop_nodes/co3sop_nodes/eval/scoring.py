"""Scores a recording of the graph: each ego's prediction (/ego/occupancy, or /cav_N/ego/occupancy where every CAV
runs an ego) against its ground truth by stamp and agent (ROS-free); with several egos, each one's table too.

Ground truth of an ego agent with no prediction at that stamp is a missed
frame: it is listed and scored as an all-empty prediction (a deployed system
that says nothing has seen nothing), never dropped. Predictions without
ground truth are listed and not scored.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from co3sop_nodes.common import topics
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.data.bags import BagReader, occupancy_labels, open_recording
from co3sop_nodes.eval.metrics import CONVENTIONS_NOTE, SCORES, Confusion, markdown_table, point
from co3sop_nodes.messages import header_stamp_ns
from co3sop_nodes.viz.bev import save_comparison


def range_of(grid: GridSpec) -> str:
    for name, spec in BENCHMARK_RANGES.items():
        if spec == grid:
            return name
    raise DatasetError(f"grid {grid} is none of the benchmark ranges ({', '.join(BENCHMARK_RANGES)})")


@dataclass
class Recording:
    predictions: dict[tuple[int, int], np.ndarray]  # (agent, stamp ns) -> (X, Y, Z) labels
    range_name: str
    truths: dict[tuple[int, int], np.ndarray]  # (agent, stamp ns) -> labels at range_name, ego agents only
    diagnostics: dict[str, list[dict[str, str]]] = field(
        default_factory=dict
    )  # status name ("ego", "vehicle cav_3") -> per-frame key/values


def _open(path: Path) -> BagReader:
    reader = open_recording(path)
    reader.open()
    return reader


def _messages(reader: BagReader, connections: list):
    """Deserialized messages of these connections, with their log time."""
    for conn, stamp, raw in reader.messages(connections=connections):
        yield conn, stamp, reader.deserialize(raw, conn, stamp)


def message_counts(path: Path) -> dict[str, int]:
    """Messages per topic of a recording, from its index (nothing is decoded)."""
    reader = _open(path)
    try:
        return {c.topic: c.msgcount for c in reader.connections}
    finally:
        reader.close()


def read_recording(path: Path, range_name: str | None = None) -> Recording:
    """Predictions, the ego agents' ground truth at the predictions' range, and the ego's diagnostics."""
    reader = _open(path)
    try:
        preds: dict[tuple[int, int], np.ndarray] = {}
        ranges = set()
        pred_conns = [c for c in reader.connections if topics.is_ego_occupancy(c.topic)]
        for conn, stamp, msg in _messages(reader, pred_conns):
            with reader.about(conn, stamp):
                labels, grid = occupancy_labels(msg)
            ranges.add(range_of(grid))
            preds[(msg.agent_id, header_stamp_ns(msg))] = labels
        if not preds and range_name is None:
            raise DatasetError(
                f"{path}: no {topics.EGO_OCCUPANCY} message, and no --range given to score missed frames"
            )
        if len(ranges) > 1:
            raise DatasetError(f"{path}: predictions at several ranges ({', '.join(sorted(ranges))})")
        recorded = ranges.pop() if ranges else None
        range_name = range_name or recorded
        if range_name not in BENCHMARK_RANGES:
            raise DatasetError(f"unknown range {range_name!r} (known: {', '.join(BENCHMARK_RANGES)})")
        if recorded is not None and range_name != recorded:
            raise DatasetError(
                f"{path}: the predictions are at {recorded}, not at the range {range_name} asked for: "
                f"score them at {recorded} (leave out --range)"
            )
        egos = {a for a, _ in preds}  # no prediction at all: every agent's ground truth counts as missed
        wanted = {topics.ground_truth(a, range_name) for a in egos}
        suffix = topics.ground_truth(0, range_name).removeprefix(topics.namespace(0))
        gt_conns = [c for c in reader.connections if c.topic in wanted or (not egos and c.topic.endswith(suffix))]
        truths = {}
        for conn, stamp, msg in _messages(reader, gt_conns):
            with reader.about(conn, stamp):
                truths[(msg.agent_id, header_stamp_ns(msg))] = occupancy_labels(msg)[0]
        diagnostics: dict[str, list[dict[str, str]]] = {}
        for _, _, msg in _messages(reader, [c for c in reader.connections if c.topic == topics.DIAGNOSTICS]):
            for status in msg.status:
                diagnostics.setdefault(status.name, []).append({kv.key: kv.value for kv in status.values})
    finally:
        reader.close()
    return Recording(preds, range_name, truths, diagnostics)


@dataclass
class Score:
    summary: dict  # metrics.Confusion.summary() over scored frames
    range_name: str
    scored: int  # frames with ground truth (predicted + missed)
    missed: list[tuple[int, int]]  # (agent, stamp) with ground truth but no prediction
    unmatched: list[tuple[int, int]]  # predictions without ground truth
    per_ego: dict[int, dict] = field(default_factory=dict)  # agent -> its own frames' summary
    counts: dict = field(default_factory=dict)  # metrics.Confusion.counts() of the scored frames, to pool over runs


def score(rec: Recording) -> Score:
    confusion, per_ego = Confusion(), {}
    missed = []
    for key in sorted(rec.truths):
        truth = rec.truths[key]
        prediction = rec.predictions.get(key)
        if prediction is None:
            missed.append(key)
            prediction = np.zeros_like(truth)
        confusion.add(prediction, truth)
        per_ego.setdefault(key[0], Confusion()).add(prediction, truth)
    unmatched = sorted(k for k in rec.predictions if k not in rec.truths)
    return Score(
        confusion.summary(),
        rec.range_name,
        len(rec.truths),
        missed,
        unmatched,
        {a: c.summary() for a, c in sorted(per_ego.items())},
        confusion.counts(),
    )


def mean_over_egos(per_ego: dict[int, dict]) -> dict[str, float]:
    """Each score (metrics.SCORES) averaged over the egos, each ego's frames pooled first."""
    return {name: float(np.mean([point(s, name) for s in per_ego.values()])) for name in SCORES}


def _pictures(rec, out: Path, keys: list[tuple[int, int]]) -> list[Path]:
    grid = BENCHMARK_RANGES[rec.range_name]
    paths = []
    for agent, stamp in keys:
        truth = rec.truths[(agent, stamp)]
        missing = (agent, stamp) not in rec.predictions
        pred = rec.predictions.get((agent, stamp), np.zeros_like(truth))
        path = out / f"bev_cav{agent}_{stamp}.png"
        save_comparison(
            truth,
            pred,
            path,
            f"cav {agent}, stamp {stamp} ns, {rec.range_name}" + (" (no prediction)" if missing else ""),
            grid.voxel_size,
        )
        paths.append(path)
    return paths


def _diagnostics_summary(diagnostics: list[dict[str, str]]) -> str:
    neighbours = [int(d.get("neighbours_used", 0)) for d in diagnostics]
    total_ms = [float(d.get("total_ms", 0.0)) for d in diagnostics]
    return (
        f"{len(diagnostics)} frames, neighbours used per frame min {min(neighbours)} / "
        f"mean {np.mean(neighbours):.2f} / max {max(neighbours)}, ego time per frame p50 {np.median(total_ms):.0f} ms"
    )


def score_recording(
    recording: Path, out: Path | None = None, range_name: str | None = None, pictures: int = 3, frames: list[int] = ()
) -> int:
    """The table of a recording printed and written to OUT/score.md and score.json, with BEV pictures of
    `pictures` frames spread over the run (or of the stamps in `frames`); OUT defaults to the recording's folder."""
    out = out or recording.parent
    out.mkdir(parents=True, exist_ok=True)
    rec = read_recording(recording, range_name)
    result = score(rec)
    name = f"{recording.stem} {result.range_name}"
    egos = {f"ego cav {a}": summary for a, summary in result.per_ego.items()} if len(result.per_ego) > 1 else {}
    columns = {**egos, (f"every ego ({name})" if egos else name): result.summary}
    lines = [
        f"### Per-class IoU (%) and mIoU: {recording.name}, {result.range_name}, {result.scored} frames",
        "",
        markdown_table(columns, every_class=True),
        "",
        CONVENTIONS_NOTE,
        "",
    ]
    if egos:
        mean = mean_over_egos(result.per_ego)
        lines += [
            f"{len(egos)} egos; the mean over egos of each one's score: "
            + ", ".join(f"{k} {100 * v:.2f}" for k, v in mean.items()),
            "",
        ]
    lines += [
        f"frames: {result.scored} with ground truth, {result.scored - len(result.missed)} predicted, "
        f"{len(result.missed)} missed (scored as empty), {len(result.unmatched)} predictions without ground truth",
    ]
    lines += [f"- missed: cav {a} at stamp {s}" for a, s in result.missed]
    lines += [f"- no ground truth: cav {a} at stamp {s}" for a, s in result.unmatched]
    statuses = sorted(n for n in rec.diagnostics if n == "ego" or n.endswith("/ego"))  # the egos' node names
    lines += [f"{status} diagnostics: {_diagnostics_summary(rec.diagnostics[status])}" for status in statuses]
    lines += [] if statuses else ["no ego diagnostics recorded"]
    keys = sorted(rec.truths)
    if frames:
        chosen = [k for k in keys if k[1] in set(frames)]
    else:
        chosen = (
            [keys[i] for i in np.unique(np.linspace(0, len(keys) - 1, pictures).round().astype(int))]
            if keys and pictures
            else []
        )
    for path in _pictures(rec, out, chosen):
        lines.append(f"picture (ground truth | prediction): {path}")
    text = "\n".join(lines)
    print(text)
    (out / "score.md").write_text(text + "\n")
    data = {
        "recording": str(recording),
        "range": result.range_name,
        "frames": result.scored,
        "missed": [list(k) for k in result.missed],
        "unmatched": [list(k) for k in result.unmatched],
        **result.summary,
        **(
            {
                "per_ego": {str(a): v for a, v in result.per_ego.items()},
                "mean_over_egos": mean_over_egos(result.per_ego),
            }
            if egos
            else {}
        ),
        "counts": result.counts,
    }
    (out / "score.json").write_text(json.dumps(data, indent=2) + "\n")
    return 0
