"""The learned wire code against the transform codec at the same bytes: the share of the collaboration gain each
keeps under request maps with a byte budget per neighbour-frame, with its 95 % interval over the split's scenarios.

    ros2_ws/benchmarks/bench_learned_codec.py --reference tiny-lidar --learned tiny-lidar-wire \
        --data data/bench --splits test \
        [--budgets 4096 8192 16384 32768] [--transform int4:8] [--levels 256] [--request-frame previous|current]
        [--answer each|union] [--fill] [--scan [--scan-level 3]]
        [--out FILE.json] [--plot FILE.png]
    ros2_ws/benchmarks/bench_learned_codec.py --replot FILE.json --plot FILE.png   # the table and curve again

Run with the workspace environment (`. ros2_ws/env.sh`). Both systems are scored against one reference: the
`--reference` model (the collaborative model the learned codes were trained from) alone and with lossless features.
Gain kept: (mIoU with the codec - reference alone) / (reference lossless - reference alone), mIoU 1..23, paired
over the same resampled scenarios. A learned model's training also goes on with its head, which may change what
its ego does alone: its own collaboration gain is (mIoU with the codec - that model alone) / (reference lossless -
reference alone), the column the goal reads. Each `--learned` model is also scored with no budget (every voxel the
ego asks for) and with every voxel of its code (dense). The transform codec runs on the reference model (codec.dtype and
codec.rank of --transform), the learned code on its own model (codec.learned); request maps are the ego's previous
frame's, as `evaluate --ablation codec` makes them, or with --request-frame current the ego's map of the same frame
(the vehicles' request_wait: a frame waits for the map made of it); with --answer union each sender's one message
for every ego of the frame is weighed by their mean need; with --fill a budget the requests leave
unspent goes to the sender's most confident other voxels (codec.fill); with --scan each sender also sends its
voxelised LiDAR scan (v2x/scan.py: one message for every ego, the voxels nearest the sensor as the budget holds
them, or all of them), which the ego's copy of the reference encodes. Prints a markdown table; --plot draws the curve
of each system's own gain kept against bytes, with the papers' message sizes (Co3SOP, CoHFF, VOGS-CP) marked.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.eval.codec_comparison import UNBOUNDED, comparison_table, label
from co3sop_nodes.eval.evaluate import REQUEST_FRAMES, evaluate, plot_codecs
from co3sop_nodes.eval.metrics import Bootstrap, point
from co3sop_nodes.inference.checkpoint import load_model, resolve_checkpoint
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.v2x.codec import FeatureCodecConfig
from co3sop_nodes.v2x.scan import ScanCodecConfig
from co3sop_nodes.v2x.sender_requests import REQUEST_ANSWERS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reference", help="the collaborative model (transform codec): a .pt file or a shipped name")
    parser.add_argument("--learned", nargs="+", help="models with a learned wire code: .pt files or shipped names")
    parser.add_argument("--data", type=Path)
    parser.add_argument("--splits", nargs="+", default=["validate"])
    parser.add_argument("--budgets", type=int, nargs="+", default=[4096, 8192, 16384, 32768])
    parser.add_argument("--transform", default="int4:8", help="the transform codec: DTYPE:RANK")
    parser.add_argument("--levels", type=int, default=256, help="request_levels of the egos")
    parser.add_argument(
        "--request-frame",
        choices=REQUEST_FRAMES,
        default="previous",
        help="the egos' maps a frame answers: of which frame",
    )
    parser.add_argument(
        "--answer",
        choices=REQUEST_ANSWERS,
        default="each",
        help="a message for each ego, or one for every ego of the frame (the vehicles' request_answer)",
    )
    parser.add_argument(
        "--fill", action="store_true", help="spend what a budget leaves past the requests (the vehicles' codec.fill)"
    )
    parser.add_argument(
        "--scan",
        action="store_true",
        help="also send each sender's voxelised scan (LiDAR models), encoded by the ego's copy of --reference",
    )
    parser.add_argument("--scan-level", type=int, default=3, help="with --scan: the scans' zstd level (codec.level)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, help="also write the result as JSON here")
    parser.add_argument("--plot", type=Path, help="also draw the curve here (PNG)")
    parser.add_argument("--replot", type=Path, help="print and draw a previous run's JSON instead of measuring")
    opts = parser.parse_args()
    if opts.replot:
        measured = json.loads(opts.replot.read_text())
    elif opts.reference and (opts.learned or opts.scan) and opts.data:
        opts.learned = opts.learned or []
        try:
            # the files to load; the results record the models as given (a shipped name stays a name)
            opts.reference_path = resolve_checkpoint(opts.reference, "--reference")
            opts.learned_paths = [resolve_checkpoint(p, "--learned") for p in opts.learned]
        except Co3sopError as e:
            parser.error(str(e))
        measured = measure(opts, parser)
    else:
        parser.error("--reference, --learned or --scan, and --data (or --replot)")
    report(measured, opts.plot)
    if opts.out:
        opts.out.parent.mkdir(parents=True, exist_ok=True)
        opts.out.write_text(json.dumps(measured, indent=2) + "\n")


def measure(opts, parser) -> dict:
    """Every run of the comparison: {"title", "reference", "splits", "runs": [one dict per system and codec]}."""
    torch.set_num_threads(opts.threads)
    reference, _ = load_model(opts.reference_path)
    learned = [(given, path, load_model(path)[0]) for given, path in zip(opts.learned, opts.learned_paths)]
    if opts.scan and reference.cfg.modality != "lidar":
        parser.error(f"--scan: --reference {opts.reference} is a {reference.cfg.modality} model (it encodes no scans)")
    for given, _, model in learned:  # checked before minutes of evaluation, not after
        if model.cfg.wire is None:
            parser.error(f"--learned {given}: has no learned wire code (train --stage wire)")
        if model.cfg.feature_grid != reference.cfg.feature_grid:
            parser.error(f"--learned {given}: another grid than --reference's ({reference.cfg.range})")
    dataset = OccupancyDataset(opts.data, opts.splits, reference.cfg)
    boot = Bootstrap(["/".join(k) for k in dataset.scenarios])
    cache: dict = {}  # the reference's vehicle outputs, shared by its runs

    def run(model, codec, cache, desc):
        return evaluate(
            model,
            dataset,
            codec=codec,
            cache=cache,
            desc=desc,
            request_levels=opts.levels,
            request_frame=opts.request_frame,
            request_answer=opts.answer,
        )

    alone = evaluate(reference, dataset, collaborators=0, cache=cache, desc="alone")[0]
    lossless = run(reference, FeatureCodecConfig("float32", "dense", codec="none"), cache, "lossless")[0]
    dtype, rank = opts.transform.split(":")
    results = []

    def add(
        system: str,
        model: str,
        codec: FeatureCodecConfig | ScanCodecConfig,
        own_alone: dict,
        confusions: dict,
        size: float,
    ):
        results.append(
            {
                "system": system,
                "model": model,
                "codec": codec.name,
                "max_bytes": codec.max_bytes,
                "bytes": size,
                "miou": point(boot.summary(confusions), "co3sop-code"),
                "alone_miou": point(boot.summary(own_alone), "co3sop-code"),
                "gain_kept": boot.ratio(confusions, lossless, alone),
                "own_gain_kept": boot.gain_ratio(confusions, own_alone, lossless, alone),
            }
        )

    for budget in opts.budgets:
        codec = FeatureCodecConfig(dtype, "request", max_bytes=budget, rank=int(rank), fill=opts.fill)
        add("transform", opts.reference, codec, alone, *run(reference, codec, cache, codec.name))
    for budget in (*opts.budgets, 0) if opts.scan else ():
        codec = ScanCodecConfig(level=opts.scan_level, max_bytes=budget)
        add(f"scan (zstd {opts.scan_level})", opts.reference, codec, alone, *run(reference, codec, cache, codec.name))
    for given, path, model in learned:
        own: dict = {}
        name = f"learned K={model.cfg.wire.rank} ({path.parent.name if path.stem == 'model' else path.stem})"
        own_alone = evaluate(model, dataset, collaborators=0, cache=own, desc=f"{name} alone")[0]
        for budget in (*opts.budgets, UNBOUNDED):
            codec = FeatureCodecConfig("int4", "request", max_bytes=budget, learned=True, fill=opts.fill)
            add(name, given, codec, own_alone, *run(model, codec, own, codec.name))
        dense = FeatureCodecConfig("int4", "dense", learned=True)
        add(name, given, dense, own_alone, *run(model, dense, own, dense.name))
    title = (
        f"{reference.cfg.name} {reference.cfg.range}, {'+'.join(opts.splits)}: {len(dataset)} samples; mIoU 1..23 "
        f"alone {100 * point(boot.summary(alone), 'co3sop-code'):.2f}, lossless "
        f"{100 * point(boot.summary(lossless), 'co3sop-code'):.2f}; request maps of {opts.levels} levels, "
        + ("each frame answering the ego's map of it" if opts.request_frame == "current" else "of the previous frame")
        + ("; one message for every ego" if opts.answer == "union" else "")
        + ("; budgets filled past the requests" if opts.fill else "")
    )
    return {"title": title, "reference": str(opts.reference), "splits": opts.splits, "runs": results}


def report(measured: dict, plot: Path | None) -> None:
    """The table (stdout) and, where `plot` is given, the curve of each system's own gain kept against bytes."""
    print("\n".join(comparison_table(measured)))
    if plot:
        plot.parent.mkdir(parents=True, exist_ok=True)
        points = {f"{r['system']}: {label(r)}": {**r, "gain_kept": r["own_gain_kept"]} for r in measured["runs"]}
        plot_codecs(plot, points, measured["title"] + "; each system's own gain kept")


if __name__ == "__main__":
    main()
