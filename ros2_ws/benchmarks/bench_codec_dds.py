"""Foundation benchmark: payload codecs and DDS one-way latency.

    ros2_ws/benchmarks/bench_codec_dds.py [--repeats 5] [--messages 100] [--out FILE.md]
    ros2_ws/benchmarks/bench_codec_dds.py --tables BAG [--repeats 30]
    ros2_ws/benchmarks/bench_codec_dds.py --shuffle BAG [--repeats 30]

Run with the workspace environment (`. ros2_ws/env.sh`). Prints markdown tables:

1. Codec encode / decode throughput (MB/s of float32 input, resp. uint8 labels)
   and size for each setting, on a 64x64x12 feature volume with 64 channels
   (the 25.6 m benchmark at 1/4 resolution) and a 256x256x24 label grid (51.2 m).
   "vs fp32" is the dense float32 volume's size over the payload's size; "codec"
   is the payload's own uncompressed over compressed size.
2. DDS one-way latency p50 / p95 between two processes for 64 KB, 1 MB and 4 MB
   messages, Fast DDS defaults vs the shipped profile, and their ratio (measured
   in the same run, since these machines are noisy).

With --tables BAG, only the payloads the demo's nodes compress each frame, made by the shipped models on the bag's
first LiDAR scan (one thread): zstd's own tables for the payload's size against the shipped setting's (at most
2^TABLE_LOG entries, `v2x/codec.py`), bytes and compression time alternating.

With --shuffle BAG, only a LiDAR vehicle's features as the demo's vehicles send them (the shipped `tiny-lidar` on
the path a vehicle takes, float16 dense, with confidence), on the bag's scans in turn: plain zstd at level 3 (the
codec before shuffle-zstd) against shuffle-zstd at level 1 (the default) and 3; payload bytes, and encoding (the
vehicle's output to its message's payloads) and decoding (payloads to features) on one thread, alternating.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import zstandard
from timing import alternated, timed

from co3sop_nodes.common.classes import NUM_CLASSES
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.data import synthetic
from co3sop_nodes.data.bags import read_scans
from co3sop_nodes.eval.codec_settings import STANDARD_FEATURE_SETTINGS
from co3sop_nodes.inference import pace
from co3sop_nodes.inference.checkpoint import load_graph_model, shipped_checkpoint
from co3sop_nodes.inference.outputs import encode_output
from co3sop_nodes.inference.predict import predict_frame
from co3sop_nodes.v2x.codec import (
    TABLE_LOG,
    FeatureCodecConfig,
    compress_payload,
    decode_features,
    decode_labels,
    encode_features,
    encode_labels,
)
from co3sop_nodes.v2x.scan import ScanCodecConfig, encode_scan

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


def real_payloads(bag: Path) -> dict[str, tuple[bytes, int]]:
    """name -> (raw bytes, zstd level) of what the demo's nodes compress each frame, from the shipped models on the
    bag's first scan: a LiDAR vehicle's features and confidence (float16, dense: the default codec), the ego's
    labels and confidence, a scan as a vehicle sends it (its bits), a camera vehicle's features."""
    scans = read_scans(bag, 1)
    if not scans:
        raise SystemExit(f"bench_codec_dds: error: {bag} holds no PointCloud2 scan")
    lidar, _ = load_graph_model(shipped_checkpoint("tiny-lidar.pt"))
    lidar.use(lidar.ego_path("auto", "auto"))
    camera, _ = load_graph_model(shipped_checkpoint("tiny.pt"))
    camera.use(camera.vehicle_path("auto", "auto"))
    inputs = pace.shaped_inputs(lidar, scan=scans[0])
    with torch.inference_mode():
        out = lidar.vehicle(**inputs)
        pred = predict_frame(lidar, out, np.eye(4), pace.shaped_neighbours(out))
        seen = camera.vehicle(**pace.shaped_inputs(camera))
    # each payload as its codec lays it out, before compression (codec "none"), at the level the nodes compress it
    raw = FeatureCodecConfig(codec="none")
    lidar_features = encode_output(out, lidar.cfg.feature_grid, raw)
    ego = encode_labels(pred.labels, lidar.cfg.grid, lidar.cfg.num_classes, confidence=pred.confidence, codec="none")
    scan = encode_scan(inputs["occupancy"][0, 0].cpu().numpy(), lidar.cfg.grid, ScanCodecConfig(codec="none"))
    level, labels = FeatureCodecConfig(codec="zstd").zstd_level, 1  # plain zstd's level, encode_labels' default
    return {
        "tiny-lidar features": (lidar_features.values, level),
        "tiny-lidar confidence": (lidar_features.confidence, level),
        "ego labels": (ego.labels, labels),
        "ego confidence": (ego.confidence, labels),
        "scan": (scan.occupancy, ScanCodecConfig().level),
        "tiny features": (encode_output(seen, camera.cfg.feature_grid, raw).values, level),
    }


def tables_table(bag: Path, repeats: int) -> str:
    torch.set_num_threads(1)
    rows = [
        f"| payload | raw KB | level | zstd's tables: KB | ms | tables of 2^{TABLE_LOG} (shipped): KB | ms | "
        "bytes: shipped / zstd's | time: zstd's / shipped |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, (raw, level) in real_payloads(bag).items():

        def zstd_tables(raw=raw, level=level):
            return zstandard.ZstdCompressor(level=level, write_checksum=True, write_content_size=True).compress(raw)

        def shipped(raw=raw, level=level):
            return compress_payload(raw, "zstd", level)

        sizes = {k: len(fn()) for k, fn in (("zstd", zstd_tables), ("shipped", shipped))}
        times = alternated({"zstd": {"c": zstd_tables}, "shipped": {"c": shipped}}, repeats)
        t_zstd, t_shipped = times["zstd", "c"], times["shipped", "c"]
        rows.append(
            f"| {name} | {len(raw) / 1024:.0f} | {level} | {sizes['zstd'] / 1024:.1f} | {1e3 * t_zstd:.2f} | "
            f"{sizes['shipped'] / 1024:.1f} | {1e3 * t_shipped:.2f} | {sizes['shipped'] / sizes['zstd']:.4f} | "
            f"{t_zstd / t_shipped:.2f}x |"
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


def shuffle_table(bag: Path, repeats: int, frames: int = 100) -> str:
    torch.set_num_threads(1)
    scans = read_scans(bag, frames)
    if not scans:
        raise SystemExit(f"bench_codec_dds: error: {bag} holds no PointCloud2 scan")
    model, _ = load_graph_model(shipped_checkpoint("tiny-lidar.pt"))
    model.use(model.vehicle_path("auto", "auto"))
    with torch.inference_mode():
        outs = [model.vehicle(**pace.shaped_inputs(model, scan=scan)) for scan in scans]
    settings = [
        FeatureCodecConfig(codec="zstd"),
        FeatureCodecConfig(),
        FeatureCodecConfig(level=3),
    ]
    grid = model.cfg.feature_grid
    groups, sizes = {}, {}
    for cfg in settings:  # each call on the next output, or message, in turn
        encoded = [encode_output(out, grid, cfg) for out in outs]
        sizes[cfg] = float(np.mean([e.payload_bytes for e in encoded]))
        inputs, messages = itertools.cycle(outs), itertools.cycle(encoded)
        groups[cfg] = {
            "encode": lambda cfg=cfg, inputs=inputs: encode_output(next(inputs), grid, cfg),
            "decode": lambda messages=messages: decode_features(next(messages)),
        }
    times = alternated(groups, repeats)
    base = settings[0]
    rows = [
        f"{len(scans)} scans of {bag}; {model.path.describe()}; one thread, median of {repeats}",
        "",
        "| codec | level | payload KB | bytes / zstd's | encode ms | decode ms | encode: zstd's / this |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for cfg in settings:
        rows.append(
            f"| {cfg.name} | {cfg.zstd_level} | {sizes[cfg] / 1024:.1f} | {sizes[cfg] / sizes[base]:.3f} | "
            f"{1e3 * times[cfg, 'encode']:.2f} | {1e3 * times[cfg, 'decode']:.2f} | "
            f"{times[base, 'encode'] / times[cfg, 'encode']:.2f}x |"
        )
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="timing repeats per codec setting")
    parser.add_argument("--messages", type=int, default=100, help="messages per DDS latency cell")
    parser.add_argument("--out", type=Path, help="also write the tables to this markdown file")
    parser.add_argument("--tables", type=Path, metavar="BAG", help="only zstd's tables on real payloads (module doc)")
    parser.add_argument("--shuffle", type=Path, metavar="BAG", help="only shuffle-zstd against zstd (module doc)")
    opts = parser.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    if opts.shuffle:
        text = "\n\n".join(["### A vehicle's features byte-shuffled", shuffle_table(opts.shuffle, opts.repeats)])
    elif opts.tables:
        text = "\n\n".join(["### zstd's tables on the payloads of a frame", tables_table(opts.tables, opts.repeats)])
    else:
        text = "\n\n".join(
            ["### Codecs", codec_tables(opts.repeats), "### DDS one-way latency", dds_table(opts.messages)]
        )
    print(text)
    if opts.out:
        opts.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
