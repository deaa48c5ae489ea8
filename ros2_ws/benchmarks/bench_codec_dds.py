"""Foundation benchmark: payload codecs and DDS one-way latency.

    ros2_ws/benchmarks/bench_codec_dds.py [--repeats 5] [--messages 100] [--out FILE.md]

Run with the workspace environment (`. ros2_ws/env.sh`). Prints markdown tables:

1. Codec encode / decode throughput (MB/s of float32 input, resp. uint8 labels)
   and size for each setting, on a 64x64x12 feature volume with 64 channels
   (the 25.6 m benchmark at 1/4 resolution) and a 256x256x24 label grid (51.2 m).
   "vs fp32" is the dense float32 volume's size over the payload's size; "codec"
   is the payload's own uncompressed over compressed size.
2. DDS one-way latency p50 / p95 between two processes for 64 KB, 1 MB and 4 MB
   messages, Fast DDS defaults vs the shipped profile, and their ratio (measured
   in the same run, since these machines are noisy).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from timing import timed

from co3sop_nodes.common.classes import NUM_CLASSES
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.data import synthetic
from co3sop_nodes.eval.codec_settings import STANDARD_FEATURE_SETTINGS
from co3sop_nodes.v2x.codec import decode_features, decode_labels, encode_features, encode_labels

HERE = Path(__file__).resolve().parent
FEATURE_GRID = GridSpec((-12.8, -12.8, -2.0), 0.4, (64, 64, 12))
CHANNELS = 64
LABEL_SETTINGS = [("none", 0), ("zstd", 1), ("zstd", 3), ("zstd", 9)]
DDS_SIZES = [("64 KB", 64 * 1024), ("1 MB", 1024 * 1024), ("4 MB", 4 * 1024 * 1024)]


def codec_tables(repeats: int) -> str:
    features, confidence = synthetic.feature_volume(FEATURE_GRID, CHANNELS, seed=0)
    fp32_bytes = features.nbytes
    rows = [
        f"Feature volume {'x'.join(map(str, FEATURE_GRID.dims))}, {CHANNELS} channels "
        f"({fp32_bytes / 1e6:.1f} MB as float32), with confidence; median of {repeats} runs.",
        "",
        "| setting | payload KB | vs fp32 | codec ratio | encode MB/s | decode MB/s | max abs error (carried) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for cfg in STANDARD_FEATURE_SETTINGS:
        t_enc, enc = timed(lambda: encode_features(features, confidence, FEATURE_GRID, cfg), repeats)
        t_dec, dec = timed(lambda: decode_features(enc), repeats)
        err = float(np.abs(dec.features - features)[:, dec.mask].max())
        rows.append(
            f"| {cfg.name} | {enc.payload_bytes / 1024:.1f} | {fp32_bytes / enc.payload_bytes:.1f}x | "
            f"{enc.raw_bytes / enc.payload_bytes:.2f}x | {fp32_bytes / 1e6 / t_enc:.0f} | "
            f"{fp32_bytes / 1e6 / t_dec:.0f} | {err:.4f} |"
        )
    grid = BENCHMARK_RANGES["51.2m"]
    labels = synthetic.street_labels(grid, seed=0)
    rows += [
        "",
        f"Label grid {'x'.join(map(str, grid.dims))} (51.2 m, {labels.nbytes / 1e6:.2f} MB as uint8); lossless.",
        "",
        "| codec | level | payload KB | ratio | encode MB/s | decode MB/s |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for codec, level in LABEL_SETTINGS:
        t_enc, enc = timed(lambda: encode_labels(labels, grid, NUM_CLASSES, codec=codec, level=level), repeats)
        t_dec, dec = timed(lambda: decode_labels(enc), repeats)
        assert np.array_equal(dec.labels, labels)
        rows.append(
            f"| {codec} | {level if codec == 'zstd' else '-'} | {enc.payload_bytes / 1024:.1f} | "
            f"{enc.raw_bytes / enc.payload_bytes:.1f}x | {labels.nbytes / 1e6 / t_enc:.0f} | {labels.nbytes / 1e6 / t_dec:.0f} |"
        )
    return "\n".join(rows)


def dds_latency(size: int, count: int, profile: str) -> list[float]:
    peer = str(HERE / "dds_latency_peer.py")
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "latency.json")
        receiver = subprocess.Popen([sys.executable, peer, "receive", str(count), out, profile])
        # 20 Hz keeps the link idle between messages: latency, not throughput.
        sender = subprocess.run([sys.executable, peer, "send", str(size), str(count), "20", profile], timeout=300)
        receiver.wait(timeout=300)
        if sender.returncode or receiver.returncode:
            raise SystemExit(f"latency peers failed for {size} B / {profile}")
        return json.loads(Path(out).read_text())


def dds_table(count: int) -> str:
    rows = [
        f"{count} messages per cell at 20 Hz, VoxelFeatures with an uncompressed payload, reliable QoS, "
        "two processes on one host (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).",
        "",
        "| size | default p50 ms | default p95 ms | shipped p50 ms | shipped p95 ms | p50 default/shipped | p95 default/shipped | received (default/shipped) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, size in DDS_SIZES:
        stats = {}
        for profile in ("default", "shipped"):
            lat = dds_latency(size, count, profile)
            stats[profile] = (np.percentile(lat, 50), np.percentile(lat, 95), len(lat))
            print(
                f"  {label} {profile}: p50 {stats[profile][0]:.2f} ms p95 {stats[profile][1]:.2f} ms", file=sys.stderr
            )
        d, s = stats["default"], stats["shipped"]
        rows.append(
            f"| {label} | {d[0]:.2f} | {d[1]:.2f} | {s[0]:.2f} | {s[1]:.2f} | {d[0] / s[0]:.1f}x | {d[1] / s[1]:.1f}x | {d[2]}/{s[2]} |"
        )
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="timing repeats per codec setting")
    parser.add_argument("--messages", type=int, default=100, help="messages per DDS latency cell")
    parser.add_argument("--out", type=Path, help="also write the tables to this markdown file")
    opts = parser.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    text = "\n\n".join(["### Codecs", codec_tables(opts.repeats), "### DDS one-way latency", dds_table(opts.messages)])
    print(text)
    if opts.out:
        opts.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
