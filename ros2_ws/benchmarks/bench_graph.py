"""Benchmark of the node graph: bytes on the wire and mIoU per feature codec, latency, CPU per node, DDS share.

    ros2_ws/benchmarks/bench_graph.py [--bag BAG] [--model tiny-lidar|CKPT] [--out results/bench_graph] [--settings ...]
    ros2_ws/benchmarks/bench_graph.py --rates 0.25 0.5 1      (rate sweep: frames fused and latency per rate)
    ros2_ws/benchmarks/bench_graph.py --paths                 (the ego's reference paths vs its fast paths)
    ros2_ws/benchmarks/bench_graph.py --device cuda --untrained paper --rates 1 2   (a preset not trained yet)

Runs the demo graph (player + 3 vehicles + ego + recorder, separate processes
over DDS, at the demo's rate) once per V2X codec setting of the neighbours
(dense, top-k by their own confidence, request maps at several byte budgets;
the ego's own encoder is lossless, as in `demo`) and once with the ego's
vehicle alone (what collaboration adds: the share of it each codec keeps,
printed and drawn against its bytes in OUT/bench_graph_codecs.png with the
papers' message sizes marked; one scene, so no interval: `evaluate --ablation
codec` has them over the test split), then reads the recordings: ego and vehicle diagnostics on /diagnostics give bytes received
per agent-frame, stage times and CPU time per frame (time.process_time of the
frame's work) and wall-clock marks on this host's clock; `score` gives mIoU.
Latency = ego's /ego/occupancy publication - the first sensor message of that
frame reaching a vehicle; DDS share = (features received by the ego - published
by the vehicle) / latency. With --rates, the demo graph (default codec) runs
once per playback rate instead, and the table gives the frames the ego fused
and the recorder recorded of the bag's, latency and CPU per node: the highest
rate with every frame fused is what the machine keeps up with (the demo's own
default rate is measured before it starts, `model.pace`). With --paths, the
graph runs twice at rate 0.04, the ego on its reference paths (PyTorch warp
and sampling, dense head, reference point cloud) and on its fast paths: each
ego stage's ratio, same run.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from ament_index_python.packages import get_package_prefix

from co3sop_nodes.common.allocation import keep_freed_memory
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.data.bags import read_scans
from co3sop_nodes.eval.codec_settings import BUDGET_FEATURE_SETTINGS, RANK_FEATURE_SETTINGS, STANDARD_FEATURE_SETTINGS
from co3sop_nodes.eval.evaluate import plot_codecs
from co3sop_nodes.eval.scoring import read_recording
from co3sop_nodes.inference import pace
from co3sop_nodes.inference.checkpoint import DEFAULT_MODEL, export_model, load_graph_model, resolve_checkpoint
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.ros import links
from co3sop_nodes.ros.demo import vehicle_model
from co3sop_nodes.ros.vehicle import CODEC_FIELDS

# The neighbours' codecs, the lossless reference first: dense, top-k by the sender's own confidence, and request maps
# (the ego's previous frame's) at several budgets, among those `evaluate --ablation codec` compares offline
OFFLINE = {cfg.name: cfg for cfg in (*STANDARD_FEATURE_SETTINGS, *BUDGET_FEATURE_SETTINGS, *RANK_FEATURE_SETTINGS)}
CODECS = [
    OFFLINE[name]
    for name in (
        "float32-dense-none",
        "float16-dense-zstd",
        "int8-dense-zstd",
        "int8-topk4096-zstd",
        "int8-topk1024-zstd",
        "int8-topk64KB-zstd",
        "int8-request64KB-zstd",
        "int4-request64KB-burst256KB-pca8-zstd",
        "int4-request32KB-pca8-zstd",
        "int4-request16KB-pca8-zstd",
    )
]
ALONE = "ego-alone-no-v2x"  # what collaboration adds: only the ego's own vehicle runs
SETTINGS = {
    **{
        cfg.name: ["--params", *(f"{param}:={getattr(cfg, field)}" for param, field in CODEC_FIELDS.items())]
        for cfg in CODECS
    },
    ALONE: ["--vehicles", "1"],
}  # name -> `demo` arguments (--params: the neighbours' vehicle parameters)
# the ego's fast paths against its reference paths (PyTorch warp and sampling, dense head, reference cloud), same codec,
# same slow rate: stage ratios
PATHS = {
    "ego-fast-paths": ["--rate", "0.04"],
    "ego-reference-paths": ["--rate", "0.04", "--ego-params", "reference_paths:=true"],
}
VEHICLE_STAGES = ("inputs_ms", "encoder_ms", "codec_ms")  # a vehicle frame's work, as its /diagnostics time it
CPU_SETTING = "int8-topk1024-zstd"  # per-node CPU is reported for the setting that meets the size goal


def pairs(text: str) -> dict[int, int]:
    return {int(a): int(b) for a, b in (x.split(":") for x in text.split(",") if x)}


def measure(mcap: Path, rate: float | None = None) -> dict:
    return measure_diagnostics(read_recording(mcap).diagnostics, rate=rate)


def measure_diagnostics(
    diagnostics: dict[str, list[dict[str, str]]], status: str = "ego", rate: float | None = None
) -> dict:
    """Bytes, latency, transport share, CPU and stage times from the nodes' /diagnostics (status name -> reports),
    of the ego whose status is named `status` ("cav_3/ego" where every CAV runs one); with the `rate` the bag was
    played at, how late its frames reached the vehicles."""
    ego = diagnostics[status]
    own = diagnostics.get(f"vehicle cav_{ego[-1]['received_wall_ns'].split(':')[0]}", [{}]) if ego else [{}]
    vehicles = {
        int(name.split("cav_")[1]): {int(d["stamp"]): d for d in ds}
        for name, ds in diagnostics.items()
        if name.startswith("vehicle") and not name.endswith(links.SUFFIX)
    }
    sizes, latency, dds_share = [], [], []
    for d in ego:
        stamp = int(d["stamp"])
        sizes += list(pairs(d["bytes_per_agent"]).values())[
            1:
        ]  # V2X only: the first is the ego's own, sent losslessly on board
        marks = {a: v[stamp] for a, v in vehicles.items() if stamp in v}
        if not marks:  # no vehicle's report of this frame recorded (a vehicle that skipped it for a newer one)
            continue
        first_input = min(int(m["first_input_wall_ns"]) for m in marks.values())
        total = int(d["published_wall_ns"]) - first_input
        latency.append(total / 1e6)
        transport = [
            r - int(marks[a]["published_wall_ns"]) for a, r in pairs(d["received_wall_ns"]).items() if a in marks
        ]
        if transport:  # none where the only features received are from a vehicle whose report of that frame was lost
            dds_share.append(max(transport) / total)
    cpu = {"ego": np.median([float(d["cpu_ms"]) for d in ego])}
    cpu.update(
        {f"vehicle {a}": np.median([float(d["cpu_ms"]) for d in v.values()]) for a, v in sorted(vehicles.items())}
    )
    stages = {
        k: float(np.median([float(d[k]) for d in ego])) for k in ("decode_ms", "fuse_ms", "head_ms", "publish_ms")
    }
    # wall time of a frame's work in each node (on a GPU, until its results are back on the host); the ego's also over
    # the frames it fused with two neighbours, the goal's case (a scene's neighbours may drive out of comm_range)
    wall = {"ego": np.median([float(d["total_ms"]) for d in ego])}
    two = [float(d["total_ms"]) for d in ego if d["neighbours_used"] == "2"]
    skipped = [int(d.get("skipped", 0)) for d in ego]  # the ego's count so far, at each fused frame
    wall.update(
        {
            f"vehicle {a}": np.median([sum(float(d[k]) for k in VEHICLE_STAGES) for d in v.values()])
            for a, v in sorted(vehicles.items())
        }
    )
    # each frame's sensors against the bag's pace: when its first input reached a vehicle, less its stamp over the
    # rate, from the run's earliest (ms; the latest vehicle's): a player or a machine that held frames back
    arrival = {}
    for v in vehicles.values() if rate else ():
        for s, d in v.items():
            arrival[s] = max(arrival.get(s, -np.inf), int(d["first_input_wall_ns"]) - s / rate)
    late = np.array([arrival[s] for s in sorted(arrival)])
    late = (late - late.min()) / 1e6 if len(late) else late
    return {
        "inputs_late_ms": (float(np.median(late)), float(late.max()), int(late.argmax()) + 1) if len(late) else None,
        "bytes_per_agent_frame": float(np.mean(sizes)) if sizes else 0.0,
        "latency_ms_p50": float(np.percentile(latency, 50)),
        "latency_ms_p95": float(np.percentile(latency, 95)),
        "dds_share_p50": float(np.median(dds_share)) if dds_share else float("nan"),
        "cpu_ms_per_frame": {k: float(v) for k, v in cpu.items()},
        "wall_ms_per_frame": {k: float(v) for k, v in wall.items()},
        "ego_ms_two_neighbours": (len(two), float(np.median(two)) if two else float("nan")),
        # where a run lost frames: the ego's slowest frames, and the fused frames its skips came before
        "ego_slowest": sorted(((float(d["total_ms"]), i + 1) for i, d in enumerate(ego)), reverse=True)[:3],
        "ego_skipped_before": [i + 1 for i, (was, now) in enumerate(zip([0, *skipped], skipped)) if now > was],
        # what a node's first frames cost beyond its later ones (first-use costs its warm-up did not take)
        "first_cpu_ms": {
            "ego": [float(d["cpu_ms"]) for d in ego[:3]],
            **{
                f"vehicle {a}": [float(d["cpu_ms"]) for _, d in sorted(v.items())[:3]]
                for a, v in sorted(vehicles.items())
            },
        },
        "vehicle_stage_ms": {
            k: float(np.median([float(d[k]) for v in vehicles.values() for d in v.values()])) for k in VEHICLE_STAGES
        },
        "ego_stage_ms": stages,
        "frames": len(ego),
        "skipped_ego": skipped[-1],
        "skipped_encoder": int(own[-1].get("skipped", 0)),
    }


ROOT = Path(__file__).resolve().parents[2]  # the repository


def run_demo(
    demo: Path, opts, name: str, args: list[str], complete: bool = True
) -> tuple[subprocess.CompletedProcess, Path]:
    """The demo graph with `args` into opts.out/name; its completed process and output folder. complete: the demo must
    succeed (every frame fused and recorded); else a recording is enough (a rate sweep counts what was fused)."""
    out = opts.out / name
    argv = [str(demo), "--out", str(out), "--quiet", "--model", opts.model, "--precision", opts.precision]
    argv += ["--device", opts.device]
    argv += ["--params", *opts.params] if opts.params else []  # before args: a setting's own --params wins
    argv += ["--ego-params", *opts.ego_params] if opts.ego_params else []
    argv += args
    # without --bag, the demo's scenario where `run_demo.sh` keeps it, from whatever folder this runs in
    argv += ["--bag", str(opts.bag)] if opts.bag else ["--frames", str(opts.frames), "--data", str(ROOT / "data/demo")]
    argv += [] if opts.bag else ["--bags", str(ROOT / "bags/demo")]
    print(f"[bench_graph] {name}: running the demo graph", flush=True)
    done = subprocess.run(argv, capture_output=True, text=True)
    if not (out / "demo.mcap").exists() or (complete and done.returncode != 0):
        print(done.stdout[-3000:], done.stderr[-3000:], file=sys.stderr)
        raise SystemExit(1)
    return done, out


def sweep(demo: Path, opts) -> int:
    """The demo graph at each rate: frames fused of the bag's, latency, CPU per node."""
    rows = [
        "| rate | frame every (s) | frames fused / in the bag | skipped: ego; its encoder | recorded | "
        "latency p50 / p95 (ms) | node wall per frame p50 (ms): ego; vehicles | "
        "CPU per frame p50 (ms): ego; vehicles |",
        "|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    kept_up, used = [], []  # used: (rate, frames fused, the graph's CPU a frame in ms) where the demo measured it
    for rate in opts.rates:
        done, out = run_demo(demo, opts, f"rate-{rate:g}", ["--rate", f"{rate:g}"], complete=False)
        frames = int(re.search(r": (\d+) frames;", done.stdout).group(1))
        recorded = re.search(r"the recording holds (?:all )?(\d+)", done.stdout + done.stderr)
        r = measure(out / "demo.mcap", rate)
        cpu, wall = r["cpu_ms_per_frame"], r["wall_ms_per_frame"]
        if r["frames"] == frames and done.returncode == 0:
            kept_up.append(rate)
        rows.append(
            f"| {rate:g} | {0.1 / rate:.2f} | {r['frames']} / {frames} | {r['skipped_ego']}; {r['skipped_encoder']} | "
            f"{recorded.group(1) if recorded else '?'} | "
            f"{r['latency_ms_p50']:.0f} / {r['latency_ms_p95']:.0f} | {wall.pop('ego'):.1f}; "
            f"{', '.join(f'{v:.1f}' for v in wall.values())} | {cpu.pop('ego'):.0f}; "
            f"{', '.join(f'{v:.0f}' for v in cpu.values())} |"
        )
        stages = ", ".join(f"{k.removesuffix('_ms')} {v:.1f}" for k, v in r["vehicle_stage_ms"].items())
        n_two, ego_two = r["ego_ms_two_neighbours"]
        processes = re.search(r"CPU a frame while the bag played \(ms\): ([^\n]*)", done.stdout)
        if processes:
            used.append((rate, r["frames"], sum(map(int, re.findall(r" (\d+)(?=,| \(|$)", processes.group(1))))))
        print(
            f"{rows[-1]}\n  vehicles' stages p50 (ms): {stages}"
            f"\n  the ego's wall p50 over the {n_two} frames fused with two neighbours (ms): {ego_two:.1f}"
            f"\n  the ego's slowest frames (#fused: ms): {', '.join(f'#{i} {ms:.0f}' for ms, i in r['ego_slowest'])}"
            + (
                f"; own frames skipped before #{', #'.join(map(str, r['ego_skipped_before']))}"
                if r["ego_skipped_before"]
                else ""
            )
            + (
                "\n  the sensors' arrival at the vehicles against the bag's pace (ms late, from the earliest): "
                "p50 {:.0f}, max {:.0f} (frame #{} of those encoded)".format(*r["inputs_late_ms"])
                if r["inputs_late_ms"]
                else ""
            )
            + "\n  CPU of the first 3 frames (ms): "
            + "; ".join(f"{k} {', '.join(f'{c:.0f}' for c in v)}" for k, v in r["first_cpu_ms"].items())
            + (f"\n  every process's CPU a frame while the bag played (ms): {processes.group(1)}" if processes else ""),
            flush=True,
        )  # as it comes: a long sweep may be cut
    print("\n".join(rows))
    if used:
        print(f"\n{against_pace(opts, done.stdout, frames, used)}")
    print(
        f"\nHighest rate with every frame fused and recorded: {max(kept_up):g}"
        if kept_up
        else "\nNo rate kept up with every frame."
    )
    return 0


def against_pace(opts, demo_output: str, frames: int, used: list[tuple[float, int, int]]) -> str:
    """The graph's CPU a frame at each rate against what `demo` measures before it chooses a rate (model.pace, here,
    after the runs: the same model, device and precision, a LiDAR vehicle on the bag's first scan) and against the
    cores: the two numbers model.pace's headroom is made of (OVERHEAD, UTILISATION)."""
    bag = Path(re.search(r"bag (\S+): \d+ frames", demo_output).group(1))
    vehicles = len(re.search(r"vehicles \[([^\]]*)\]", demo_output).group(1).split(","))
    keep_freed_memory()  # as the demo measures
    checkpoint = resolve_checkpoint(opts.model, "--model")
    model, _ = load_graph_model(checkpoint)
    model.use(model.ego_path(opts.device, opts.precision, what="--"))
    precision = dict(p.partition(":=")[::2] for p in opts.params).get("precision", opts.precision)
    scan = next(iter(read_scans(bag, 1)), None) if model.cfg.modality == "lidar" else None
    cost = pace.frame_cost(model, scan=scan, vehicles=vehicle_model(model, checkpoint, opts.device, precision))
    work_ms = 1e3 * pace.graph_work(cost, vehicles)[0]
    cores = pace.cores()
    rows = [
        f"The work model.pace measures: vehicle {1e3 * cost.vehicle_s:.1f} ms, ego {1e3 * cost.ego_s:.1f} ms, the "
        f"recorder's pictures {1e3 * cost.recording_s:.1f} ms; {work_ms:.0f} ms a frame for {vehicles} vehicles and "
        f"the ego (headroom {pace.HEADROOM:.2f} = OVERHEAD {pace.OVERHEAD} / UTILISATION {pace.UTILISATION})\n",
        f"| rate | frames fused / {frames} | the graph's CPU a frame (ms) | over the work measured | "
        f"share of the {cores} cores |",
        "|---:|---:|---:|---:|---:|",
    ]
    for rate, fused, cpu_ms in used:
        share = cpu_ms / (1e3 * 0.1 / rate * cores)
        rows.append(f"| {rate:g} | {fused} | {cpu_ms} | {cpu_ms / work_ms:.2f} | {100 * share:.0f} % |")
    return "\n".join(rows)


def paths(demo: Path, opts) -> int:
    """The ego's reference paths against its fast paths, same graph, same rate: stage times and their ratio."""
    results = {name: measure(run_demo(demo, opts, name, args)[1] / "demo.mcap") for name, args in PATHS.items()}
    ref, fast = results["ego-reference-paths"], results["ego-fast-paths"]
    rows = ["| ego (ms per frame, p50) | reference paths | fast paths | reference / fast |", "|---|---:|---:|---:|"]
    pairs_ = [(k.removesuffix("_ms"), ref["ego_stage_ms"][k], fast["ego_stage_ms"][k]) for k in ref["ego_stage_ms"]]
    pairs_ += [
        ("CPU", ref["cpu_ms_per_frame"]["ego"], fast["cpu_ms_per_frame"]["ego"]),
        ("latency (first sensor message -> /ego/occupancy)", ref["latency_ms_p50"], fast["latency_ms_p50"]),
    ]
    rows += [f"| {k} | {a:.1f} | {b:.1f} | {a / b:.1f}x |" for k, a, b in pairs_]
    print("\n".join(rows))
    opts.out.mkdir(parents=True, exist_ok=True)
    (opts.out / "bench_graph_paths.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0


def untrained_checkpoint(name: str, out: Path) -> Path:
    """A checkpoint of preset `name` with its initial weights (seed 0), written into `out`."""
    torch.manual_seed(0)
    path = out / f"{name}-untrained.pt"
    export_model(path, build_model(preset(name)), {"untrained": True, "seed": 0})
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[1])
    parser.add_argument("--bag", type=Path, help="default: the demo scenario")
    parser.add_argument("--frames", type=int, default=10, help="frames of the generated demo scenario (without --bag)")
    parser.add_argument(
        "--precision", default="auto", help="every node's inference precision, as `demo --precision` takes it"
    )
    parser.add_argument("--out", type=Path, default=Path("results/bench_graph"))
    parser.add_argument(
        "--model", default=DEFAULT_MODEL, help="every node's model, as `demo --model` takes it (default: the demo's)"
    )
    parser.add_argument("--device", default="cpu", help="where every node's model runs, as `demo --device` takes it")
    parser.add_argument(
        "--untrained",
        metavar="PRESET",
        help="time a preset nobody has trained yet: its initial weights (seed 0) instead of --model; latency and "
        "throughput only, its mIoU means nothing",
    )
    parser.add_argument("--params", nargs="*", default=[], help="the vehicles' parameters, as `demo --params`")
    parser.add_argument("--ego-params", nargs="*", default=[], help="the ego's parameters, as `demo --ego-params`")
    parser.add_argument("--settings", nargs="*", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument(
        "--rates", nargs="*", type=float, help="sweep these playback rates (default codec) instead of the settings"
    )
    parser.add_argument(
        "--paths", action="store_true", help="the ego's reference paths against its fast paths instead of the settings"
    )
    opts = parser.parse_args()
    demo = Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes", "demo")
    if opts.untrained:
        try:
            opts.model = str(untrained_checkpoint(opts.untrained, opts.out))
        except Co3sopError as exc:
            parser.error(f"--untrained: {exc}")
    if opts.rates:
        return sweep(demo, opts)
    if opts.paths:
        return paths(demo, opts)
    results = {}
    for name in opts.settings:
        out = run_demo(demo, opts, name, SETTINGS[name])[1]
        score = json.loads((out / "score.json").read_text())
        results[name] = {
            **measure(out / "demo.mcap"),
            "miou": score["co3sop-readme"]["miou"],
            "miou_code": score["co3sop-code"]["miou"],
        }
    ref = results[opts.settings[0]]
    alone = results.get(ALONE)
    # gain kept: (codec - alone) / (lossless - alone) in mIoU 1..23, as `evaluate --ablation codec` computes it, on this
    # one scene (no interval: that needs the test split's scenarios, offline)
    gain = ref["miou_code"] - alone["miou_code"] if alone else float("nan")
    for r in results.values():
        r["gain_kept"] = (r["miou_code"] - alone["miou_code"]) / gain if alone and gain > 0 else float("nan")
    print(
        f"\n| V2X feature codec (neighbours) | bytes per neighbour-frame | vs {opts.settings[0]} | mIoU "
        f"co3sop-readme | change (points) | "
        "mIoU co3sop-code | gain kept (%) | latency p50 / p95 (ms) | DDS share p50 |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in results.items():
        print(
            f"| {name} | {r['bytes_per_agent_frame']:,.0f} | "
            f"{r['bytes_per_agent_frame'] / ref['bytes_per_agent_frame'] if ref['bytes_per_agent_frame'] else 0:.3f} | "
            f"{100 * r['miou']:.2f} | {100 * (r['miou'] - ref['miou']):+.2f} | {100 * r['miou_code']:.2f} | "
            f"{100 * r['gain_kept']:.0f} | "
            f"{r['latency_ms_p50']:.0f} / {r['latency_ms_p95']:.0f} | {100 * r['dds_share_p50']:.1f} % |"
        )
    opts.out.mkdir(parents=True, exist_ok=True)
    if alone and gain > 0:
        curve = {
            name: {
                "bytes": r["bytes_per_agent_frame"],
                "gain_kept": {"ratio": r["gain_kept"], "ci95": (r["gain_kept"], r["gain_kept"])},
            }
            for name, r in results.items()
            if name != ALONE
        }
        plot_codecs(
            opts.out / "bench_graph_codecs.png",
            curve,
            "the node graph on the demo scene: gain kept per neighbours' codec (one scene, no interval)",
        )
        print(f"\nThe curve: {opts.out / 'bench_graph_codecs.png'}")
    cpu_setting = CPU_SETTING if CPU_SETTING in results else opts.settings[-1]
    r = results[cpu_setting]
    print(
        f"\nCPU time per frame (ms, median) with {cpu_setting}: "
        + ", ".join(f"{k} {v:.0f}" for k, v in r["cpu_ms_per_frame"].items())
    )
    print(
        "ego stages (ms, median): "
        + ", ".join(f"{k.removesuffix('_ms')} {v:.0f}" for k, v in r["ego_stage_ms"].items())
    )
    (opts.out / "bench_graph.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
