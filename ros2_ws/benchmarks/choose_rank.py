"""Choosing the transform coding's rank, its precision and the burst of a byte budget on `validate`: the share of the
collaboration gain that request maps keep under a byte budget, per `codec.rank`, with no budget at all (every voxel the
ego asked for), and with the budget an average per message whose single messages may take up to a burst
(`codec.burst_bytes`), each at `codec.dtype` --dtype; each with the request maps' levels of --levels (the ego's
`request_levels`) and the vehicles' answers of --answers (`request_answer`: a message for each ego, or one for all
by the union of their requests, every agent an ego).

    ros2_ws/benchmarks/choose_rank.py --model src/co3sop_nodes/checkpoints/tiny-lidar.pt --data data/bench \
        [--splits validate] [--dtype int8] [--budget 65536] [--ranks 4 6 8 10 16] [--unbounded 0 8] [--bursts] \
        [--burst-ranks 8] [--levels 256 4 2] [--answers each union] [--out FILE.json]

Run with the workspace environment (`. ros2_ws/env.sh`). Gain kept: (codec - alone) / (lossless - alone) in mIoU
1..23, as `evaluate --ablation codec` computes it (its request maps: the ego's previous frame's), with its 95 %
interval over the split's scenarios. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import torch

from co3sop_nodes.eval.evaluate import evaluate
from co3sop_nodes.eval.metrics import Bootstrap, point
from co3sop_nodes.inference.checkpoint import load_model
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.v2x.codec import QUANTIZED, FeatureCodecConfig
from co3sop_nodes.v2x.sender_requests import REQUEST_ANSWERS

UNBOUNDED = 2**31 - 1  # the largest codec.max_bytes: every requested voxel fits


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--splits", nargs="+", default=["validate"])
    parser.add_argument("--dtype", choices=QUANTIZED, default="int8", help="codec.dtype of every run")
    parser.add_argument("--budget", type=int, default=65536, help="codec.max_bytes of the request maps")
    parser.add_argument("--ranks", type=int, nargs="+", default=[4, 6, 8, 10, 16])
    parser.add_argument("--unbounded", type=int, nargs="*", default=[0, 8], help="ranks also run with no budget")
    parser.add_argument(
        "--bursts", type=int, nargs="*", default=[], help="codec.burst_bytes also run (at --burst-rank)"
    )
    parser.add_argument("--burst-ranks", type=int, nargs="+", default=[8], help="the ranks run with each burst")
    parser.add_argument("--levels", type=int, nargs="+", default=[256], help="request_levels of the egos")
    parser.add_argument("--answers", nargs="+", choices=REQUEST_ANSWERS, default=["each"], help="request_answer")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, help="also write the result as JSON here")
    opts = parser.parse_args()
    torch.set_num_threads(opts.threads)
    model, _ = load_model(opts.model)
    dataset = OccupancyDataset(opts.data, opts.splits, model.cfg)
    boot = Bootstrap(["/".join(k) for k in dataset.scenarios])
    cache: dict = {}  # the vehicle halves' outputs, shared by every run
    alone = evaluate(model, dataset, collaborators=0, cache=cache, desc="alone")[0]
    lossless = evaluate(
        model, dataset, codec=FeatureCodecConfig("float32", "dense", codec="none"), cache=cache, desc="lossless"
    )[0]
    runs = (
        [(rank, opts.budget, 0) for rank in (0, *opts.ranks)]
        + [(rank, UNBOUNDED, 0) for rank in opts.unbounded]
        + [(rank, opts.budget, burst) for rank in opts.burst_ranks for burst in opts.bursts]
    )
    rows, results = [], []
    for (rank, budget, burst), levels, answer in itertools.product(runs, opts.levels, opts.answers):
        cfg = FeatureCodecConfig(opts.dtype, "request", max_bytes=budget, burst_bytes=burst, rank=rank)
        confusions, size = evaluate(
            model,
            dataset,
            codec=cfg,
            cache=cache,
            desc=f"{cfg.name} {levels} levels, {answer}",
            request_levels=levels,
            request_answer=answer,
        )
        kept = boot.ratio(confusions, lossless, alone)
        results.append(
            {
                "dtype": opts.dtype,
                "rank": rank,
                "max_bytes": budget,
                "burst_bytes": burst,
                "request_levels": levels,
                "request_answer": answer,
                "bytes": size,
                "miou": point(boot.summary(confusions), "co3sop-code"),
                "gain_kept": kept,
            }
        )
        limit = "none" if budget == UNBOUNDED else f"{budget:,}" + (f" on average, {burst:,} at most" if burst else "")
        rows.append(
            f"| {opts.dtype} | {rank or '- (channels)'} | {limit} | {levels} | {answer} | {size:,.0f} | "
            f"{100 * results[-1]['miou']:.2f} | {100 * kept['ratio']:.0f} [{100 * kept['ci95'][0]:.0f}, "
            f"{100 * kept['ci95'][1]:.0f}] |"
        )
    title = (
        f"{model.cfg.name} {model.cfg.range}, {'+'.join(opts.splits)}: {len(dataset)} samples; mIoU 1..23 alone "
        f"{100 * point(boot.summary(alone), 'co3sop-code'):.2f}, lossless "
        f"{100 * point(boot.summary(lossless), 'co3sop-code'):.2f}"
    )
    print(
        "\n".join(
            [
                title,
                "",
                "| codec.dtype | codec.rank | codec.max_bytes | request_levels | request_answer | bytes per "
                "neighbour-frame | mIoU 1..23 | gain kept (%) [95 % interval] |",
                "|---|---|---:|---:|---|---:|---:|---|",
                *rows,
            ]
        )
    )
    if opts.out:
        opts.out.parent.mkdir(parents=True, exist_ok=True)
        opts.out.write_text(
            json.dumps({"title": title, "model": str(opts.model), "splits": opts.splits, "runs": results}, indent=2)
            + "\n"
        )


if __name__ == "__main__":
    main()
