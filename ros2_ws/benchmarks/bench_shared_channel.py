"""Every CAV an ego on one shared V2X channel: CAVs x medium rate, per ego, against the same graph with no channel.

    ros2_ws/benchmarks/bench_shared_channel.py --bag BAG [--cavs 2 3 4 5] [--medium 3 6 12] [--answers union each]
        [--request-levels 2] [--model tiny-lidar|CKPT] [--out results/bench_shared_channel]

Needs root, iproute2 and nftables (co3sop_nodes/v2x/channel.py). For each number of CAVs N (the bag's first N),
`demo --egos all` runs every CAV's ego and vehicle:
- with no channel, every ego alone (ego parameter max_collaborators 0): the floor of each ego's score;
- with no channel and lossless features (float32, dense): the ceiling;
- on one shared medium of M Mbit/s of real time (`--channel-shared`, scaled by the play rate the demo measures, so
  the bytes per frame are real time's), per answer mode (vehicle parameter request_answer): request maps of
  --request-levels levels, int4 coefficients at rank 8, each message's budget (codec.max_bytes) its share of the
  medium: 80 % of the M Mbit/s at 10 Hz split over the copies DDS sends (one per ego it reaches, unicast): N x (N-1)
  copies a frame with one message for every ego (union), N x (N-1)^2 with a message for each ego (each: every ego
  receives every ego's message).
Per ego, from the launcher's copy of every node's /diagnostics and `score`: neighbour-frames fused (% of those
within comm range: fused, late or never received), latency
p50 / p95 (first sensor message of a frame at a vehicle -> that ego's occupancy published), bytes per neighbour-frame
received, and the share of the collaboration gain it kept, (channel - alone) / (lossless - alone) in mIoU 1..23, on
this one scene (no interval: `evaluate` and choose_rank.py have them over a split's scenarios); per vehicle, the
bytes it sent per frame. Prints a markdown table (also OUT/bench_shared_channel.md and .json).
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
from co3sop_nodes.v2x.sender_requests import REQUEST_ANSWERS

FRAME_RATE = 10.0  # Hz: the sensors' rate, at which the medium's bytes per frame are counted
SHARE = 0.8  # of the medium for feature payloads: the rest for request maps, RTPS headers, acknowledgements


def budget(medium_mbit: float, cavs: int, answer: str) -> int:
    """Bytes one message may take: its share of the medium's bytes per frame over the copies sent."""
    copies = cavs * (cavs - 1) * ((cavs - 1) if answer == "each" else 1)
    return int(SHARE * medium_mbit * 1e6 / 8 / FRAME_RATE / copies)


def fused_share(reports: list[dict[str, str]]) -> float:
    """Neighbour-frames fused of those due: the neighbours within comm range, fused, late or never received (a
    neighbour beyond comm range is not due)."""
    count = lambda text: len([x for x in text.split(",") if x])
    used = sum(int(d["neighbours_used"]) for d in reports)
    due = used + sum(count(d["neighbours_missing"]) + count(d["neighbours_silent"]) for d in reports)
    return used / due if due else 1.0


def run(demo: str, opts, out: Path, cavs: int, extra: list[str]) -> dict:
    argv = [demo, "--bag", str(opts.bag), "--out", str(out), "--quiet", "--model", opts.model, "--egos", "all"]
    argv += ["--vehicles", str(cavs), *extra]
    print(f"[bench_shared_channel] {cavs} CAVs: {' '.join(extra) or 'no channel'}", flush=True)
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        print(done.stdout[-3000:], done.stderr[-3000:], file=sys.stderr)
        raise SystemExit(1)
    diagnostics = json.loads((out / "diagnostics.json").read_text())
    score = json.loads((out / "score.json").read_text())
    medium = re.search(r"packets the shared medium dropped [^:]*: (\d+)", done.stdout)
    rate = float(re.search(r"playing the bag at rate ([0-9.]+)", done.stdout).group(1))
    egos = {}
    for name, reports in diagnostics.items():
        if not name.endswith("/ego"):
            continue
        cav = int(name.split("/")[0].removeprefix("cav_"))
        measured = measure_diagnostics(diagnostics, name)
        egos[cav] = {
            "fused": fused_share(reports),
            "latency_p50": measured["latency_ms_p50"],
            "latency_p95": measured["latency_ms_p95"],
            "bytes": measured["bytes_per_agent_frame"],
            "frames": len(reports),
            "miou23": score["per_ego"][str(cav)]["co3sop-code"]["miou"] if "per_ego" in score else None,
        }
    sent = {  # the payloads of its messages a frame, before DDS copies each to every ego it reaches
        int(name.removeprefix("vehicle cav_")): float(np.mean([int(d["payload_bytes"]) for d in reports]))
        for name, reports in diagnostics.items()
        if name.startswith("vehicle")
    }
    return {"rate": rate, "egos": egos, "sent": sent, "medium_drops": int(medium.group(1)) if medium else None}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bag", type=Path, required=True, help="a CAV bag with at least max(--cavs) CAVs")
    parser.add_argument("--cavs", type=int, nargs="+", default=[2, 3, 4, 5])
    parser.add_argument("--medium", type=float, nargs="+", default=[3, 6, 12], help="shared rate, Mbit/s real time")
    parser.add_argument("--answers", nargs="+", choices=REQUEST_ANSWERS, default=["union"])
    parser.add_argument("--request-levels", type=int, default=2, help="the egos' request_levels")
    parser.add_argument("--out", type=Path, default=Path("results/bench_shared_channel"))
    parser.add_argument("--model", default=DEFAULT_MODEL, help="every node's model, as `demo --model` takes it")
    opts = parser.parse_args()
    demo = str(Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes", "demo"))
    levels = f"request_levels:={opts.request_levels}"
    rows = [
        f"Every CAV an ego; bag {opts.bag}; model {opts.model}; request maps of {opts.request_levels} levels, "
        "int4 coefficients at rank 8, each message's budget its share of the medium (see the script).",
        "",
        "| CAVs | medium (Mbit/s, real time) | answer | budget per message (bytes) | play rate | ego | neighbour-frames "
        "fused (%) | latency p50 / p95 (ms) | bytes per neighbour-frame | gain kept (%) | vehicle's message bytes "
        "per frame | packets the medium dropped |",
        "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    results = []
    for n in opts.cavs:
        alone = run(demo, opts, opts.out / f"{n}cavs-alone", n, ["--ego-params", "max_collaborators:=0"])
        lossless = run(
            demo,
            opts,
            opts.out / f"{n}cavs-lossless",
            n,
            ["--params", "codec.dtype:=float32", "codec.compression:=none"],
        )
        for medium in opts.medium:
            for answer in opts.answers:
                size = budget(medium, n, answer)
                codec = ["codec.selection:=request", "codec.dtype:=int4", "codec.rank:=8", f"codec.max_bytes:={size}"]
                extra = ["--channel-rate", f"{medium:g}", "--channel-shared", "--params", *codec]
                extra += [f"request_answer:={answer}", "--ego-params", levels]
                cell = run(demo, opts, opts.out / f"{n}cavs-{medium:g}mbit-{answer}", n, extra)
                for cav, ego in sorted(cell["egos"].items()):
                    floor, ceiling = alone["egos"][cav]["miou23"], lossless["egos"][cav]["miou23"]
                    ego["gain_kept"] = (ego["miou23"] - floor) / (ceiling - floor) if ceiling != floor else None
                    kept = "-" if ego["gain_kept"] is None else f"{100 * ego['gain_kept']:.0f}"
                    rows.append(
                        f"| {n} | {medium:g} | {answer} | {size:,} | {cell['rate']:g} | {cav} | "
                        f"{100 * ego['fused']:.0f} | {ego['latency_p50']:.0f} / {ego['latency_p95']:.0f} | "
                        f"{ego['bytes']:,.0f} | {kept} | {cell['sent'][cav]:,.0f} | {cell['medium_drops']} |"
                    )
                kept = [e["gain_kept"] for e in cell["egos"].values() if e["gain_kept"] is not None]
                rows.append(
                    f"| {n} | {medium:g} | {answer} | {size:,} | {cell['rate']:g} | mean | "
                    f"{100 * np.mean([e['fused'] for e in cell['egos'].values()]):.0f} | | | "
                    f"{np.mean(kept) * 100:.0f} | | |"
                )
                results.append(
                    {
                        "cavs": n,
                        "medium": medium,
                        "answer": answer,
                        "budget": size,
                        **cell,
                        "alone": alone,
                        "lossless": lossless,
                    }
                )
    text = "\n".join(rows)
    print(text)
    opts.out.mkdir(parents=True, exist_ok=True)
    (opts.out / "bench_shared_channel.md").write_text(text + "\n")
    (opts.out / "bench_shared_channel.json").write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
