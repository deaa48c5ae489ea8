"""Benchmark through the emulated V2X channel: link rate x loss x codec, the demo graph once per cell.

    ros2_ws/benchmarks/bench_channel.py [--bag BAG] [--link 6 27 100] [--loss 0 5] [--reliability reliable best_effort]
        [--play-rate 0.25] [--repeats 1] [--model tiny-lidar|CKPT] [--out results/bench_channel]

Needs root, iproute2 and nftables (co3sop_nodes/channel.py). Each cell runs
`demo --channel-rate LINK --channel-loss LOSS --rate PLAY_RATE` with the
neighbours' codec, so the link rate is scaled by the play rate and a cell
stands for real time (27 Mbit/s at rate 0.25 is a 6.75 Mbit/s link), and the
features' QoS (`features_reliability` of the neighbours and the ego: reliable
resends lost fragments, best effort drops a sample with one lost). Per cell, from the launcher's copy of every
node's /diagnostics (OUT/diagnostics.json) and `score`: the share of
neighbour-frames fused within the ego's max_wait, bytes per neighbour-frame
received, latency p50 / p95 (first sensor message of a frame reaching a
vehicle -> /ego/occupancy published; bench_graph's definition), mIoU, and the
packets the channel dropped. Prints a markdown table (also OUT/bench_channel.md).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
from ament_index_python.packages import get_package_prefix
from bench_graph import measure_diagnostics

from co3sop_nodes.inference.checkpoint import DEFAULT_MODEL
from co3sop_nodes.ros.dds import RELIABILITIES

CODECS = {  # the neighbours' vehicle parameters
    "int8 dense": ["codec.dtype:=int8", "codec.selection:=dense"],
    "request map, 64 KB": ["codec.dtype:=int8", "codec.selection:=request", "codec.max_bytes:=65536"],
    "request map, 64 KB, rank 8": [
        "codec.dtype:=int8",
        "codec.selection:=request",
        "codec.max_bytes:=65536",
        "codec.rank:=8",
    ],
    "request map, 64 KB with 256 KB bursts, rank 8, int4": [
        "codec.dtype:=int4",
        "codec.selection:=request",
        "codec.max_bytes:=65536",
        "codec.burst_bytes:=262144",
        "codec.rank:=8",
    ],
}


def run_demo(argv: list[str]) -> subprocess.CompletedProcess:
    """One `demo` run (its output captured); the benchmark stops, showing the end of that output, if it fails."""
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        print(done.stdout[-3000:], done.stderr[-3000:], file=sys.stderr)
        raise SystemExit(1)
    return done


def cell(demo: str, opts, link: float, loss: float, codec: str, reliability: str, run: int = 0) -> dict:
    out = (
        opts.out / f"link{link:g}-loss{loss:g}-{codec.replace(' ', '').replace(',', '-')}-{reliability}"
        f"{f'-run{run}' if run else ''}"
        f"{'-shared' if opts.shared else ''}"
    )
    qos = f"features_reliability:={reliability}"
    argv = (
        [
            demo,
            "--out",
            str(out),
            "--quiet",
            "--model",
            opts.model,
            "--rate",
            f"{opts.play_rate:g}",
            "--channel-rate",
            f"{link:g}",
            "--channel-loss",
            f"{loss:g}",
            "--params",
            *CODECS[codec],
            qos,
            "--ego-params",
            qos,
        ]
        + (["--bag", str(opts.bag)] if opts.bag else [])
        + (["--channel-shared"] if opts.shared else [])
    )
    print(f"[bench_channel] {link:g} Mbit/s, {loss:g} % loss, {codec}, {reliability}", flush=True)
    done = run_demo(argv)
    diagnostics = json.loads((out / "diagnostics.json").read_text())
    ego = diagnostics["ego"]
    neighbours = len(diagnostics) - 2  # every vehicle but the ego's own encoder
    fused = sum(int(d["neighbours_used"]) for d in ego) / max(1, neighbours * len(ego))
    measured = measure_diagnostics(diagnostics)
    score = json.loads((out / "score.json").read_text())
    lost = re.search(r"packets dropped by the channel: (.*)", done.stdout)
    medium = re.search(r"packets the shared medium dropped [^:]*: (\d+)", done.stdout)
    return {
        "link": link,
        "loss": loss,
        "codec": codec,
        "reliability": reliability,
        "fused": fused,
        "bytes": measured["bytes_per_agent_frame"],
        "latency_p50": measured["latency_ms_p50"],
        "latency_p95": measured["latency_ms_p95"],
        "miou24": score["co3sop-readme"]["miou"],
        "miou23": score["co3sop-code"]["miou"],
        "lost": ", ".join([*([lost.group(1)] if lost else []), *([f"medium {medium.group(1)}"] if medium else [])])
        or "-",
        "frames": len(ego),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bag", type=Path, help="a CAV bag (default: the demo's scenario)")
    parser.add_argument("--link", type=float, nargs="+", default=[6, 27, 100], help="link rates, Mbit/s of real time")
    parser.add_argument("--loss", type=float, nargs="+", default=[0, 5], help="packet loss, percent")
    parser.add_argument("--codecs", nargs="+", default=list(CODECS), choices=list(CODECS))
    parser.add_argument(
        "--reliability", nargs="+", default=list(RELIABILITIES), choices=list(RELIABILITIES), help="the features' QoS"
    )
    parser.add_argument("--play-rate", type=float, default=0.25, help="the bag's play rate (the link is scaled by it)")
    parser.add_argument("--repeats", type=int, default=1, help="runs of each cell (a row each, then their median)")
    parser.add_argument(
        "--shared",
        action="store_true",
        help="every CAV on one shared medium of the link's rate (demo --channel-shared)",
    )
    parser.add_argument("--out", type=Path, default=Path("results/bench_channel"))
    parser.add_argument(
        "--model", default=DEFAULT_MODEL, help="every node's model, as `demo --model` takes it (default: the demo's)"
    )
    opts = parser.parse_args()
    demo = str(Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes", "demo"))
    rows = [
        f"Play rate {opts.play_rate:g} (the link is LINK x {opts.play_rate:g} Mbit/s); 3 vehicles + ego"
        + (
            "; every CAV on one shared medium of the link's rate."
            if opts.shared
            else ", each CAV on a link of its own."
        ),
        "",
        "| link (Mbit/s, real time) | loss (%) | neighbours' codec | features QoS | neighbour-frames fused "
        "(%) | bytes per neighbour-frame | "
        "latency p50 / p95 (ms) | mIoU 24 classes | mIoU 1..23 | packets lost by the channel |",
        "|---:|---:|---|---|---:|---:|---:|---:|---:|---|",
    ]
    results = []
    for link in opts.link:
        for loss in opts.loss:
            for codec in opts.codecs:
                for reliability in opts.reliability:
                    runs = [
                        cell(demo, opts, link, loss, codec, reliability, run)
                        for run in (range(1, opts.repeats + 1) if opts.repeats > 1 else [0])
                    ]
                    results.extend(runs)
                    labelled = [(f"{codec} (run {i})" if opts.repeats > 1 else codec, r) for i, r in enumerate(runs, 1)]
                    if opts.repeats > 1:
                        median = {
                            k: float(np.median([r[k] for r in runs]))
                            for k in ("fused", "bytes", "latency_p50", "latency_p95", "miou24", "miou23")
                        }
                        labelled.append((f"{codec} (median of {opts.repeats})", {**median, "lost": "-"}))
                    rows += [
                        f"| {link:g} | {loss:g} | {label} | {reliability.replace('_', ' ')} | "
                        f"{100 * r['fused']:.0f} | {r['bytes']:,.0f} | "
                        f"{r['latency_p50']:.0f} / {r['latency_p95']:.0f} | {100 * r['miou24']:.2f} | "
                        f"{100 * r['miou23']:.2f} | {r['lost']} |"
                        for label, r in labelled
                    ]
    text = "\n".join(rows)
    print(text)
    opts.out.mkdir(parents=True, exist_ok=True)
    (opts.out / "bench_channel.md").write_text(text + "\n")
    (opts.out / "bench_channel.json").write_text(json.dumps(results, indent=1) + "\n")
    return 0 if all(np.isfinite(r["latency_p50"]) for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
