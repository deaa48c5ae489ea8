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
from pathlib import Path

from co3sop_nodes.cli.common import run
from co3sop_nodes.eval.scoring import score_recording


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="score", description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("recording", type=Path, help="an MCAP file written by `recorder`")
    parser.add_argument(
        "--out", type=Path, help="where score.md / score.json / pictures go (default: beside the recording)"
    )
    parser.add_argument("--range", dest="range_name", help="benchmark range (default: the predictions')")
    parser.add_argument("--pictures", type=int, default=3, help="BEV pictures of this many frames spread over the run")
    parser.add_argument("--frames", type=int, nargs="*", default=[], help="stamps (ns) to picture instead")
    opts = parser.parse_args(args)
    return score_recording(opts.recording, opts.out, opts.range_name, opts.pictures, opts.frames)


entry = run(main)
