"""`score`: the paper-style table of a recorded run, and BEV pictures of prediction vs ground truth.

    ros2 run co3sop_nodes score results/demo/demo.mcap [--out results/demo] [--pictures 3] [--frames STAMP ...]

Pairs each /ego/occupancy with the ego's ground truth of the same stamp and
prints per-class IoU and mIoU in the three conventions (co3sop_nodes.eval.metrics)
at the recorded range, as markdown (also written to OUT/score.md) and JSON
(OUT/score.json). Frames with ground truth but no prediction count as missed:
they are listed and scored as all-empty predictions. Pictures show, per
chosen frame, ground truth (left) and prediction (right) from above.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from co3sop_nodes.viz.bev import save_comparison
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.eval.metrics import CONVENTIONS_NOTE, markdown_table
from co3sop_nodes.eval.scoring import read_recording, score
from co3sop_nodes.cli.common import run


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
    if not diagnostics:
        return "no ego diagnostics recorded"
    neighbours = [int(d.get("neighbours_used", 0)) for d in diagnostics]
    total_ms = [float(d.get("total_ms", 0.0)) for d in diagnostics]
    return (f"ego diagnostics: {len(diagnostics)} frames, neighbours used per frame min {min(neighbours)} / "
            f"mean {np.mean(neighbours):.2f} / max {max(neighbours)}, ego time per frame p50 {np.median(total_ms):.0f} ms")


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="score", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path, help="an MCAP file written by `recorder`")
    parser.add_argument("--out", type=Path, help="where score.md / score.json / pictures go (default: beside the recording)")
    parser.add_argument("--range", dest="range_name", help="benchmark range (default: the predictions')")
    parser.add_argument("--pictures", type=int, default=3, help="BEV pictures of this many frames spread over the run")
    parser.add_argument("--frames", type=int, nargs="*", default=[], help="stamps (ns) to picture instead")
    opts = parser.parse_args(args)
    out = opts.out or opts.recording.parent
    out.mkdir(parents=True, exist_ok=True)
    rec = read_recording(opts.recording, opts.range_name)
    result = score(rec)
    name = f"{opts.recording.stem} {result.range_name}"
    lines = [f"### Per-class IoU (%) and mIoU: {opts.recording.name}, {result.range_name}, {result.scored} frames", "",
             markdown_table({name: result.summary}, every_class=True), "", CONVENTIONS_NOTE, "",
             f"frames: {result.scored} with ground truth, {result.scored - len(result.missed)} predicted, "
             f"{len(result.missed)} missed (scored as empty), {len(result.unmatched)} predictions without ground truth"]
    lines += [f"- missed: cav {a} at stamp {s}" for a, s in result.missed]
    lines += [f"- no ground truth: cav {a} at stamp {s}" for a, s in result.unmatched]
    lines.append(_diagnostics_summary(rec.diagnostics.get("ego", [])))
    keys = sorted(rec.truths)
    if opts.frames:
        chosen = [k for k in keys if k[1] in set(opts.frames)]
    else:
        chosen = [keys[i] for i in np.unique(np.linspace(0, len(keys) - 1, opts.pictures).round().astype(int))] if keys and opts.pictures else []
    for path in _pictures(rec, out, chosen):
        lines.append(f"picture (ground truth | prediction): {path}")
    text = "\n".join(lines)
    print(text)
    (out / "score.md").write_text(text + "\n")
    data = {"recording": str(opts.recording), "range": result.range_name, "frames": result.scored,
            "missed": [list(k) for k in result.missed], "unmatched": [list(k) for k in result.unmatched], **result.summary}
    (out / "score.json").write_text(json.dumps(data, indent=2) + "\n")
    return 0


entry = run(main)
