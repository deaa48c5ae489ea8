"""Every CAV an ego on one shared V2X channel: CAVs x medium rate, per ego, against the same graph with no channel.

    ros2_ws/benchmarks/bench_shared_channel.py --bag BAG [BAG ...] [--cavs 2 3 4 5] [--medium 3 6 12]
        [--answers union each] [--request-levels 4] [--rate-scale 0.5] [--model tiny-lidar|CKPT]
        [--reference CKPT] [--multicast] [--payload-share 0.6] [--answer-ms MS] [--request-wait 0.5] [--maps-first]
        [--fill] [--send features|scan] [--out results/bench_shared_channel]

Needs root, iproute2 and nftables (co3sop_nodes/v2x/channel.py). For each bag (one scene; a scene of fewer than N
CAVs is listed, not run) and number of CAVs N (the bag's first N), `demo --egos all` runs every CAV's ego and
vehicle, at one play rate for N (the rate the demo measures for N vehicles and N egos, times --rate-scale: the
codec and the channel cost more than the model's time the demo measures, and an ego behind its input skips frames,
which `score` counts as empty):
- with no channel, every ego alone (ego parameter max_collaborators 0): the floor of each ego's score;
- with no channel and lossless features (float32, dense): the ceiling;
- on one shared medium of M Mbit/s of real time (`--channel-shared`, scaled by the play rate, so the bytes per
  frame are real time's, as are DDS's reliability timers and the egos' waits for a neighbour: `demo`), per answer
  mode (vehicle parameter request_answer): request maps of --request-levels levels, int4 coefficients at rank 8
  (or the model's learned wire code, codec.learned, where it has one: the alone and lossless runs are then
  --reference's, and the gain on the channel is counted from the model's own egos alone), each message's budget
  (codec.max_bytes) its share of the medium: --payload-share (60 %) of the M Mbit/s at 10 Hz, less the request
  maps (N x (N-1) a frame), split over the copies of feature messages DDS sends (one per ego a message reaches,
  unicast): N x (N-1) a frame with one message for every ego (union), N x (N-1)^2 with a message for each ego
  (each: every ego receives every ego's message); with --multicast (`demo --channel-multicast`) each message (and
  each request map) crosses the medium once: N feature messages a frame (union), N x (N-1) (each). A cell whose
  budget holds no voxel (the vehicle would refuse the codec) is listed, not run. M = 0: no channel and no
  budget (every voxel an ego asks for), the codec's ceiling in the graph. With --request-wait F each vehicle's
  frame waits up to F of a frame period for the request map every ego makes of that frame (vehicle parameter
  request_wait, in real time at the play rate); without, a frame answers the maps of the egos' previous frame.
  With --maps-first (and --multicast) the request maps cross the medium before the features waiting on it
  (`demo --channel-maps-first`). With --fill what a message's budget leaves past the requests goes to the
  vehicle's most confident other voxels (codec.fill). With --send scan (a LiDAR model) each vehicle sends its
  voxelised scan instead (vehicle parameter send, co3sop_msgs/VoxelScan: one message for every ego, zstd level
  15, the voxels nearest the sensor as its budget holds them), each ego encodes its neighbours' scans with its
  own copy of the model and makes no request maps; the play rate then counts that work too.
Per ego, from the launcher's copy of every node's /diagnostics and `score`: its frames missed (skipped to stay
current, which `score` counts as empty predictions), neighbour-frames fused (% of those within comm range: fused,
late or never received), latency p50 / p95 (first sensor message of a frame at a vehicle -> that ego's occupancy
published), bytes per neighbour-frame received, its collaboration gain (lossless - alone, mIoU 1..23), the gain
on the channel (channel - alone) and the share kept where the gain is at least half a point (every ego together:
the gains summed), per scene; per vehicle, the bytes it sent per frame; the medium: packets it dropped (beyond its
queue), KB it carried a frame of the bag and its load (the share of its rate used from the channel's start to the
graph's stop, start-up included). Then, over the scenes, per CAVs x medium x answer: the gain kept with every
ego's frames of a scene pooled (as `evaluate` pools every CAV as the ego in turn) and its 95 % interval over the
scenes, and the egos that keep 90 % of their own gain. Prints markdown tables (also OUT/bench_shared_channel.md
and .json). Resumable: a run whose OUT/<bag name>/<cell>/cell.json exists is read, not run again.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np
from ament_index_python.packages import get_package_prefix
from bench_channel import run_demo
from bench_graph import measure_diagnostics

from co3sop_nodes.common.errors import CodecError
from co3sop_nodes.eval.codec_comparison import UNBOUNDED
from co3sop_nodes.eval.metrics import Bootstrap, Confusion
from co3sop_nodes.eval.scoring import read_recording, score
from co3sop_nodes.inference.checkpoint import DEFAULT_MODEL, load_graph_model, resolve_checkpoint
from co3sop_nodes.model.path import inference_path
from co3sop_nodes.ros.demo import bag_period, measured_rate
from co3sop_nodes.ros.graph import bag_contents
from co3sop_nodes.ros.vehicle import CODEC_FIELDS, SCAN_FIELDS, SENDS
from co3sop_nodes.v2x.codec import FeatureCodecConfig, check_codec_for
from co3sop_nodes.v2x.scan import ScanCodecConfig, encode_scan
from co3sop_nodes.v2x.sender_requests import REQUEST_ANSWERS

FRAME_RATE = 10.0  # Hz: the sensors' rate, at which the medium's bytes per frame are counted
# of the medium for payloads by default: the rest for RTPS headers, heartbeats, acknowledgements and slack, as the
# messages of every CAV queue on it at each frame's start and must cross within the frame
PAYLOAD_SHARE = 0.6
# a RequestMap message's bytes at 51.2 m (tiny-lidar's 64x64x6 feature grid) by request_levels: the 95th percentile
# over the validate split's frames at the egos' zstd level (bench_request_bytes.py)
REQUEST_BYTES = {2: 600, 4: 1_400, 8: 3_300, 16: 5_700, 256: 17_500}
MIN_GAIN = 0.005  # mIoU: the least collaboration gain whose share is reported
# zstd level of the vehicles' scans (--send scan), chosen on validate: the fastest that keeps 99 % of the scans
# within 8 KB, at 5 ms a scan, with LiDARs of the benchmark's and of the real dataset's density (bench_scan_bytes.py)
SCAN_LEVEL = 15


def codec_of(size: int, cfg, fill: bool = False, scans: bool = False) -> FeatureCodecConfig | ScanCodecConfig:
    """The vehicles' codec: with `scans` their scans in `size` bytes; else request maps, `size` bytes per message
    (the rest of it filled past the requests with `fill`), the model's learned wire code where it has one, else
    int4 coefficients at rank 8."""
    if scans:
        return ScanCodecConfig(level=SCAN_LEVEL, max_bytes=max(1, size))
    if cfg.wire is not None:
        return FeatureCodecConfig("int4", "request", max_bytes=max(1, size), learned=True, fill=fill)
    return FeatureCodecConfig("int4", "request", max_bytes=max(1, size), rank=8, fill=fill)


def carries_voxels(codec: FeatureCodecConfig | ScanCodecConfig, cfg) -> bool:
    """A message of `codec` can carry a voxel of the model's features or scan (the vehicle refuses a features codec
    that cannot, and sends no scan that does not fit)."""
    try:
        if isinstance(codec, ScanCodecConfig):
            encode_scan(np.zeros(cfg.grid.dims, bool), cfg.grid, codec)
            return True
        check_codec_for(codec, cfg.wire.rank if codec.learned else cfg.embed_dims, cfg.feature_grid)
    except CodecError:
        return False
    return True


def budget(
    medium_mbit: float,
    cavs: int,
    answer: str,
    levels: int,
    multicast: bool = False,
    share: float = PAYLOAD_SHARE,
    maps: bool = True,
) -> int:
    """Bytes one message may take: the medium's payload bytes per frame (`share` of it), less every ego's request map
    to every vehicle (where the egos make them: `maps`), over the copies of feature messages DDS sends (one per ego
    a message reaches, or a vehicle a request map reaches; one for all of them with multicast)."""
    if medium_mbit == 0:  # no channel: every voxel an ego asks for
        return UNBOUNDED
    maps_bytes = cavs * (1 if multicast else cavs - 1) * REQUEST_BYTES[levels] if maps else 0
    payload = share * medium_mbit * 1e6 / 8 / FRAME_RATE - maps_bytes
    messages = cavs * ((cavs - 1) if answer == "each" else 1)
    return int(payload / (messages * (1 if multicast else cavs - 1)))


def channel_args(medium_mbit: float, opts) -> list[str]:
    """demo's options for one shared medium of `medium_mbit` Mbit/s of real time (none for 0: no channel)."""
    if not medium_mbit:
        return []
    args = ["--channel-rate", f"{medium_mbit:g}", "--channel-shared"] + (
        ["--channel-multicast"] if opts.multicast else []
    )
    args += ["--channel-maps-first"] if opts.maps_first else []
    return args + ([] if opts.answer_ms is None else ["--channel-answer-ms", f"{opts.answer_ms:g}"])


def kept_share(kept: float, gain: float) -> str:
    """The share of a collaboration gain kept, in %, where the gain is at least MIN_GAIN (else the ratio means
    nothing: an ego whose neighbours add nothing)."""
    return f"{100 * kept / gain:.0f}" if gain >= MIN_GAIN else "-"


def fused_share(reports: list[dict[str, str]]) -> float:
    """Neighbour-frames fused of those due: the neighbours within comm range, fused, late or never received (a
    neighbour beyond comm range is not due)."""
    count = lambda text: len([x for x in text.split(",") if x])
    used = sum(int(d["neighbours_used"]) for d in reports)
    due = used + sum(count(d["neighbours_missing"]) + count(d["neighbours_silent"]) for d in reports)
    return used / due if due else 1.0


def run(demo: str, bag: Path, out: Path, cavs: int, extra: list[str], model: str) -> dict:
    """One demo run, measured (kept in OUT/cell.json: a run that finished is not run again)."""
    kept = out / "cell.json"
    if kept.exists():
        cell = json.loads(kept.read_text())
        if "counts" not in cell:  # kept before the score had its counts: scored again from the recording
            cell["counts"] = score(read_recording(out / "demo.mcap")).counts
            kept.write_text(json.dumps(cell, indent=1) + "\n")
        return {
            **cell,
            "egos": {int(k): v for k, v in cell["egos"].items()},
            "sent": {int(k): v for k, v in cell["sent"].items()},
        }
    argv = [demo, "--bag", str(bag), "--out", str(out), "--quiet", "--model", model, "--egos", "all"]
    argv += ["--vehicles", str(cavs), *extra]
    print(f"[bench_shared_channel] {bag.name}, {cavs} CAVs: {' '.join(extra) or 'no channel'}", flush=True)
    done = run_demo(argv)
    diagnostics = json.loads((out / "diagnostics.json").read_text())
    scored = json.loads((out / "score.json").read_text())
    carried = re.search(r"the shared medium carried [0-9.,]+ KB, ([0-9.,]+) KB a frame \((\d+) % of", done.stdout)
    medium = re.search(r"packets it dropped [^:]*: (\d+)", done.stdout)
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
            "miou23": scored["per_ego"][str(cav)]["co3sop-code"]["miou"] if "per_ego" in scored else None,
            "missed": sum(1 for agent, _ in scored["missed"] if agent == cav),  # skipped to stay current: scored empty
        }
    sent = {  # the payloads of its messages a frame, before DDS copies each to every ego it reaches
        int(name.removeprefix("vehicle cav_")): float(np.mean([int(d["payload_bytes"]) for d in reports]))
        for name, reports in diagnostics.items()
        if name.startswith("vehicle")
    }
    cell = {
        "rate": rate,
        "egos": egos,
        "sent": sent,
        "medium_drops": int(medium.group(1)) if medium else None,
        "medium_kb": float(carried.group(1).replace(",", "")) if carried else None,
        "medium_load": int(carried.group(2)) if carried else None,
        "counts": scored["counts"],  # every ego's frames pooled: the scene's confusion, for intervals over scenes
    }
    kept.write_text(json.dumps(cell, indent=1) + "\n")
    return cell


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--bag",
        type=Path,
        nargs="+",
        required=True,
        help="CAV bags, one scene each (one with fewer than N CAVs: not run)",
    )
    parser.add_argument("--cavs", type=int, nargs="+", default=[2, 3, 4, 5])
    parser.add_argument(
        "--medium",
        type=float,
        nargs="+",
        default=[3, 6, 12],
        help="shared rate, Mbit/s real time; 0: no channel, every voxel an ego asks for (the codec's graph ceiling)",
    )
    parser.add_argument("--answers", nargs="+", choices=REQUEST_ANSWERS, default=["union"])
    parser.add_argument(
        "--request-levels", type=int, choices=sorted(REQUEST_BYTES), default=4, help="the egos' request_levels"
    )
    parser.add_argument(
        "--rate-scale", type=float, default=0.5, help="the play rate: the demo's measured one for N CAVs times this"
    )
    parser.add_argument(
        "--payload-share", type=float, default=PAYLOAD_SHARE, help="of the medium's bytes a frame for the messages"
    )
    parser.add_argument(
        "--answer-ms", type=float, help="demo --channel-answer-ms (default: the demo's, the medium's queue time)"
    )
    parser.add_argument("--out", type=Path, default=Path("results/bench_shared_channel"))
    parser.add_argument("--model", default=DEFAULT_MODEL, help="every node's model, as `demo --model` takes it")
    parser.add_argument(
        "--multicast", action="store_true", help="feature messages multicast (demo --channel-multicast): sent once each"
    )
    parser.add_argument(
        "--reference",
        help="the model of the alone and lossless runs (default: --model): the one a learned code was trained from",
    )
    parser.add_argument(
        "--request-wait",
        type=float,
        default=0.0,
        help="of a frame period: how long a vehicle's frame waits for the egos' maps of it (0: answers earlier maps)",
    )
    parser.add_argument(
        "--maps-first", action="store_true", help="request maps cross the medium first (needs --multicast)"
    )
    parser.add_argument(
        "--fill", action="store_true", help="a budget the requests leave unspent goes to other voxels (codec.fill)"
    )
    parser.add_argument(
        "--send", choices=SENDS, default="features", help="what the vehicles send (vehicle parameter send)"
    )
    opts = parser.parse_args()
    if opts.maps_first and not opts.multicast:
        parser.error("--maps-first needs --multicast")
    if opts.send == "scan" and (opts.answers != ["union"] or opts.maps_first or opts.fill or opts.request_wait):
        parser.error(
            "--send scan: one scan for every ego, no request maps (no --answers each, --maps-first, "
            "--fill or --request-wait)"
        )
    demo = str(Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes", "demo"))
    model = load_graph_model(resolve_checkpoint(opts.model, "--model"))[0].use(inference_path("cpu", "auto"))
    scenes = {bag: bag_contents(bag) for bag in opts.bag}  # bag -> (CAV ids, frames)
    if len({bag.name for bag in scenes}) < len(scenes):
        parser.error("--bag: two bags of one name (each scene's runs are kept in OUT/<bag name>)")
    periods = {bag_period(bag, frames) for bag, (_, frames) in scenes.items()}
    if len(periods) > 1:
        parser.error(f"--bag: the bags' frame periods differ ({sorted(periods)} s): one play rate serves them all")
    period = periods.pop()
    # every run of N CAVs at one rate: the demo's for N vehicles and N egos, slowed by --rate-scale, so that the
    # codec's and the channel's cost on top of the model's leaves the egos every frame (a skipped one is scored
    # empty); the medium is scaled by it, so its bytes per frame are real time's
    scans = opts.send == "scan"
    if scans and model.cfg.modality != "lidar":
        parser.error(f"--send scan: --model {opts.model} is a {model.cfg.modality} model (a LiDAR one sends scans)")
    rates = {
        n: f"{max(0.01, opts.rate_scale * measured_rate(model, n, period, egos=n, scans=scans)):.3f}" for n in opts.cavs
    }
    rows = [header(opts, model.cfg), *TABLE_HEAD]
    results = []
    for bag, (cavs, _) in scenes.items():
        for n in opts.cavs:
            if len(cavs) < n:
                rows.append(padded([bag.name, str(n), f"not run: the scene has {len(cavs)} CAVs"]))
                continue
            results += scene_cells(demo, opts, model.cfg, bag, n, rates[n], period, rows)
    text = "\n".join(rows + ["", *over_scenes(results)])
    print(text)
    opts.out.mkdir(parents=True, exist_ok=True)
    (opts.out / "bench_shared_channel.md").write_text(text + "\n")
    (opts.out / "bench_shared_channel.json").write_text(json.dumps(results, indent=1) + "\n")
    return 0


def header(opts, cfg) -> str:
    """What every cell shares."""
    if opts.send == "scan":
        sent = (
            f"each vehicle's scan (zstd level {SCAN_LEVEL}), encoded by every ego's copy of the model, no request maps"
        )
        sent += ", multicast" if opts.multicast else ", unicast"
    else:
        sent = (
            f"request maps of {opts.request_levels} levels, "
            + ("its learned wire code" if cfg.wire else "int4 coefficients at rank 8")
            + (", features and request maps multicast" if opts.multicast else ", unicast")
            + (", request maps crossing the medium first" if opts.maps_first else "")
            + (", budgets filled past the requests" if opts.fill else "")
            + (
                f", each frame answering the egos' maps of it (waiting up to {opts.request_wait:g} of a frame)"
                if opts.request_wait
                else ", each frame answering the egos' maps of their previous frame"
            )
        )
    return (
        f"Every CAV an ego; bags {', '.join(str(b) for b in opts.bag)}; model {opts.model} (alone and lossless: "
        f"{opts.reference or opts.model}); {sent}"
        + ("" if opts.answer_ms is None else f", DDS readers answering heartbeats after {opts.answer_ms:g} ms")
        + ", each message's budget its share of the medium (see the script).\n"
    )


TABLE_HEAD = [
    "| scene | CAVs | medium (Mbit/s, real time) | answer | budget per message (bytes) | play rate | ego | "
    "frames missed | neighbour-frames fused (%) | latency p50 / p95 (ms) | bytes per neighbour-frame | "
    "collaboration gain, lossless (points) | gain on the channel (points) | gain kept (%) | "
    "vehicle's message bytes per frame | packets the medium dropped | medium: KB a frame (% of its rate) |",
    "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
]


def padded(cells: list[str]) -> str:
    """A table row of `cells`, the columns after them empty."""
    return "| " + " | ".join(cells + [""] * (TABLE_HEAD[1].count("|") - 1 - len(cells))) + " |"


def scene_cells(demo: str, opts, cfg, bag: Path, n: int, rate: str, period: float, rows: list[str]) -> list[dict]:
    """One scene's runs of its first `n` CAVs: alone, lossless, and each medium x answer cell (rows appended)."""
    out = opts.out / bag.name
    reference = opts.reference or opts.model
    opts_rate = ["--rate", rate]
    floor = [*opts_rate, "--ego-params", "max_collaborators:=0"]
    alone = run(demo, bag, out / f"{n}cavs-alone", n, floor, reference)
    # a learned code's model trained its head on: its egos alone are its own floor (the gain stays the reference's)
    own_alone = run(demo, bag, out / f"{n}cavs-alone-own", n, floor, opts.model) if opts.reference else alone
    ceiling = [*opts_rate, "--params", "codec.dtype:=float32", "codec.compression:=none"]
    lossless = run(demo, bag, out / f"{n}cavs-lossless", n, ceiling, reference)
    results = []
    for medium in opts.medium:
        for answer in opts.answers:
            scans = opts.send == "scan"
            size = budget(medium, n, answer, opts.request_levels, opts.multicast, opts.payload_share, not scans)
            shown, size_shown = (f"{medium:g}", f"{size:,}") if medium else ("none", "every voxel asked for")
            first = f"| {bag.name} | {n} | {shown} | {answer} | {size_shown} |"
            # no channel: every voxel asked for (or the whole scan), no budget
            codec = codec_of(size, cfg, opts.fill and bool(medium), scans)
            if not carries_voxels(codec, cfg):
                why = "not run: a message of this budget carries no voxel (the request maps and the basis take it)"
                rows.append(padded([bag.name, str(n), shown, answer, size_shown, "", "", why]))
                continue
            fields = {p: f for p, f in CODEC_FIELDS.items() if not scans or f in SCAN_FIELDS}
            params = [f"{p}:={str(getattr(codec, f)).lower()}" for p, f in fields.items()]
            extra = [*opts_rate, *channel_args(medium, opts), "--params", *params, f"send:={opts.send}"]
            extra += [f"request_answer:={answer}"]
            if opts.request_wait:  # of sensor time, in real time at the play rate
                extra += [f"request_wait:={opts.request_wait * period / float(rate):.3f}"]
            maps = "request_maps:=false" if scans else f"request_levels:={opts.request_levels}"
            extra += ["--ego-params", maps]
            answer_delay = "" if opts.answer_ms is None or not medium else f"-{opts.answer_ms:g}ms"
            wait = f"-wait{opts.request_wait:g}" if opts.request_wait else ""
            maps_first = "-mapsfirst" if opts.maps_first and medium else ""
            fill = "-fill" if not scans and codec.fill else ""
            sent = "-scan" if scans else ""
            name = f"{n}cavs-{medium:g}mbit-{answer}-{size}B{answer_delay}{wait}{maps_first}{fill}{sent}"
            cell = run(demo, bag, out / name, n, extra, opts.model)
            load = "-" if cell.get("medium_load") is None else f"{cell['medium_kb']:,.0f} ({cell['medium_load']})"
            for cav, ego in sorted(cell["egos"].items()):
                ego["gain"] = lossless["egos"][cav]["miou23"] - alone["egos"][cav]["miou23"]
                ego["kept"] = ego["miou23"] - own_alone["egos"][cav]["miou23"]
                rows.append(
                    f"{first} {cell['rate']:g} | {cav} | {ego['missed']} | {100 * ego['fused']:.0f} | "
                    f"{ego['latency_p50']:.0f} / {ego['latency_p95']:.0f} | "
                    f"{ego['bytes']:,.0f} | {100 * ego['gain']:+.2f} | {100 * ego['kept']:+.2f} | "
                    f"{kept_share(ego['kept'], ego['gain'])} | {cell['sent'][cav]:,.0f} | {cell['medium_drops']} | "
                    f"{load} |"
                )
            egos = cell["egos"].values()
            rows.append(
                f"{first} {cell['rate']:g} | all | {sum(e['missed'] for e in egos)} | "
                f"{100 * np.mean([e['fused'] for e in egos]):.0f} | | | "
                f"{100 * sum(e['gain'] for e in egos):+.2f} | {100 * sum(e['kept'] for e in egos):+.2f} | "
                f"{kept_share(sum(e['kept'] for e in egos), sum(e['gain'] for e in egos))} | | | |"
            )
            results.append(
                {
                    "scene": bag.name,
                    "cavs": n,
                    "medium": medium,
                    "answer": answer,
                    "budget": size,
                    **cell,
                    "alone": alone,
                    "own_alone": own_alone,
                    "lossless": lossless,
                }
            )
    return results


def over_scenes(results: list[dict]) -> list[str]:
    """Per CAVs x medium x answer over the scenes run: the gain kept, every ego's frames of a scene pooled (as
    `evaluate` pools every CAV as the ego in turn), with its 95 % interval over the scenes (metrics.Bootstrap,
    seed 0: the channel's mIoU over the model's own egos alone against the reference's lossless over its alone,
    paired); the egos whose own gain is at least MIN_GAIN and keep 90 % of it; frames missed; neighbour-frames
    fused."""
    groups: dict[tuple, list[dict]] = {}
    for r in results:
        groups.setdefault((r["cavs"], r["medium"], r["answer"]), []).append(r)
    lines = [
        "Over the scenes: every ego's frames of a scene pooled, 95 % interval over the scenes (bootstrap, seed 0).",
        "",
        "| CAVs | medium (Mbit/s, real time) | answer | scenes | egos | frames missed | neighbour-frames fused (%) | "
        "gain kept (%) [95 % interval] | egos keeping 90 % of their gain |",
        "|---:|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for (n, medium, answer), cells in sorted(groups.items()):
        scenes = [c["scene"] for c in cells]
        of = lambda run: {c["scene"]: Confusion.from_counts(c[run]["counts"] if run else c["counts"]) for c in cells}
        ratio = Bootstrap(scenes).gain_ratio(of(None), of("own_alone"), of("lossless"), of("alone"))
        egos = [e for c in cells for e in c["egos"].values()]
        counted = [e for e in egos if e["gain"] >= MIN_GAIN]
        lines.append(
            f"| {n} | {f'{medium:g}' if medium else 'none'} | {answer} | {len(scenes)} | {len(egos)} | "
            f"{sum(e['missed'] for e in egos)} | {100 * np.mean([e['fused'] for e in egos]):.0f} | "
            f"{100 * ratio['ratio']:.0f} [{100 * ratio['ci95'][0]:.0f}, {100 * ratio['ci95'][1]:.0f}] | "
            f"{sum(e['kept'] >= 0.9 * e['gain'] for e in counted)} of {len(counted)} |"
        )
    return lines


if __name__ == "__main__":
    sys.exit(main())
