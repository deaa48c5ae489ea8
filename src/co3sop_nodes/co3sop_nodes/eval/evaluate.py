"""Per-class IoU and mIoU of a model on a split with bootstrap intervals over scenarios, and the paper's ablations
(the `evaluate` command, co3sop_nodes.cli.evaluate, explains each)."""

from __future__ import annotations

import json
import math
import textwrap
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from co3sop_nodes.common.bounded_cache import BoundedCache
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.common.progress import progress
from co3sop_nodes.eval.codec_settings import BUDGET_FEATURE_SETTINGS, RANK_FEATURE_SETTINGS, STANDARD_FEATURE_SETTINGS
from co3sop_nodes.eval.controls import INPUT_CONTROLS, ControlledInputs
from co3sop_nodes.eval.metrics import CONVENTIONS, Bootstrap, Confusion, difference_table, markdown_table, point
from co3sop_nodes.inference.checkpoint import load_model, resolve_checkpoint, shipped_checkpoint
from co3sop_nodes.inference.inputs import to_batch
from co3sop_nodes.inference.outputs import through_codec, through_scan
from co3sop_nodes.inference.predict import predict_frame
from co3sop_nodes.model.co3sop import Co3SOP, VehicleOutput
from co3sop_nodes.model.path import InferencePath, cpu_units, inference_path
from co3sop_nodes.train.dataset import OccupancyDataset, Sample, early_fused
from co3sop_nodes.v2x.codec import FeatureCodecConfig, decode_request, encode_request
from co3sop_nodes.v2x.neighbours import COMM_RANGE, nearest_collaborators, noisy_relative
from co3sop_nodes.v2x.request_map import request_for_neighbour, request_of
from co3sop_nodes.v2x.scan import ScanCodecConfig
from co3sop_nodes.v2x.sender_budget import SenderBudgets
from co3sop_nodes.v2x.sender_requests import union_request

# the frame whose request maps a frame answers: the one before (a map reaches a neighbour a frame late), or its own
REQUEST_FRAMES = ("previous", "current")


def data_origin(root: Path) -> dict:
    """The evaluated data as the results page names it: its root, and whether this project's simulator wrote
    it (every scenario's data_protocol.yaml carries the simulator's settings)."""
    protocols = list(Path(root).glob("*/*/data_protocol.yaml"))
    return {"root": str(root), "generated": bool(protocols) and all("co3sop_sim:" in p.read_text() for p in protocols)}


def vehicle_cache(max_bytes: int = 4 << 30) -> BoundedCache:
    """The vehicle halves' outputs kept between samples and calls, at most `max_bytes` of them."""
    return BoundedCache(
        max_bytes,
        lambda out: out.features.nbytes + out.confidence.nbytes + (0 if out.code is None else out.code.nbytes),
    )


@torch.no_grad()
def evaluate(
    model: Co3SOP,
    dataset: OccupancyDataset,
    collaborators: int | None = None,
    mu: float = 0.0,
    sigma: float = 0.0,
    codec: FeatureCodecConfig | ScanCodecConfig | None = None,
    seed: int = 0,
    desc: str = "evaluate",
    cache: dict | None = None,
    inputs: str = "real",
    where: Callable[[Sample], bool] | None = None,
    later_frames: dict | None = None,
    path: InferencePath | None = None,
    labels: dict | None = None,
    indices: list[int] | None = None,
    request_levels: int = 256,
    request_answer: str = "each",
    request_frame: str = "previous",
    vehicles: Co3SOP | None = None,
) -> tuple[dict, float]:
    """({"split/scenario": Confusion}, mean bytes per collaborator frame sent) over every sample of the dataset.

    `cache` keeps the vehicle halves' outputs between calls (they do not depend on the ego's settings);
    `inputs` is one of learn.controls.INPUT_CONTROLS; `where` keeps only the samples it accepts (judged on the
    sample with every collaborator in range, whatever `collaborators` is). `later_frames`, where given, is
    filled as the result with the samples whose ego was there the frame before (those a request map reaches:
    every one but the ego's first frame of a scenario). `path`, where given, is the inference path the model
    runs on from now on (`Co3SOP.use`: a cache is valid for one path only); `labels`, where given, is filled with
    each sample's predicted labels by sample index; `indices`, where given, are the samples evaluated (default:
    every one); `request_levels`: the levels a request map's need is sent with (the ego's parameter);
    `request_answer`: "each" (a message per ego, chosen by its request) or "union" (a sender's one message for every
    agent of the frame, each an ego, chosen by the union of their requests within the communication range: the
    vehicle's parameter request_answer where every CAV runs an ego); `request_frame`: the frame whose request maps a
    frame answers, "previous" (the graph's default: a map reaches a neighbour a frame late) or "current" (the
    vehicles' request_wait: a frame waits for the maps made of it). `vehicles`, where given, is the model (the same
    weights on a path of its own, as vehicle nodes run on theirs) whose vehicle halves make every agent's features;
    `model` then fuses them, as an ego node.
    """
    if request_frame not in REQUEST_FRAMES:
        raise Co3sopError(f"request_frame {request_frame!r}: one of {', '.join(REQUEST_FRAMES)}")
    early = model.cfg.early_fusion
    if early and codec is not None:
        raise Co3sopError(
            f"{model.cfg.name}: an early-fusion model merges the collaborators' scans, it receives no "
            f"features to encode"
        )
    scans = isinstance(codec, ScanCodecConfig)
    if scans and model.cfg.modality != "lidar":
        raise Co3sopError(f"{model.cfg.name}: a {model.cfg.modality} model encodes no LiDAR scans ({codec.name})")
    rng = np.random.default_rng(seed)
    if path is not None:
        model.use(path)
    vehicles = model if vehicles is None else vehicles
    device, grid = model.path.torch_device, model.cfg.feature_grid
    confusions, sent = {}, []
    senders: dict[tuple, SenderBudgets] = {}  # (scenario, sender) -> its byte budgets, one per ego
    broadcast: dict[tuple, tuple[VehicleOutput, int]] = {}  # (frame, sender) -> its message for every ego (union)
    cache = vehicle_cache() if cache is None else cache
    controlled = ControlledInputs(dataset, inputs)
    indices = range(len(dataset)) if indices is None else indices
    bar = progress(len(indices), desc, "sample")
    for i in indices:
        if where is not None and not where(dataset.sample(i)):
            bar.update(1)
            continue
        sample = dataset.sample(i, collaborators)
        f, _ = dataset.index[i]
        position = {cav: j for j, cav in enumerate(dataset.frames[f].cav_ids)}

        def vehicle(cav: int, frame: int = f, j: int | None = None) -> VehicleOutput:
            key = (frame, cav, inputs)
            out = cache.get(key)
            if out is None:
                out = vehicles.vehicle(**to_batch(controlled(frame, position[cav] if j is None else j), device))
                cache[key] = out  # kept while the cache has room
            return out

        def previous_frame(frame: int, cav: int) -> int | None:
            """`cav`'s index among the agents one frame before `frame` in the same scenario, if it was there."""
            if frame == 0 or dataset.frames[frame - 1].key[:2] != dataset.frames[frame].key[:2]:
                return None
            return next((k for k, c in enumerate(dataset.frames[frame - 1].cav_ids) if c == cav), None)

        def request_made(frame: int, cav: int) -> tuple[np.ndarray, np.ndarray] | None:
            """(request, world_from_ego) of `cav` that frame `frame` answers (of `frame`, or of the frame before in
            the same scenario, if it was there)."""
            made, j = (frame, position[cav]) if request_frame == "current" else (frame - 1, previous_frame(frame, cav))
            if j is None:
                return None
            sent = encode_request(request_of(vehicle(cav, made, j).confidence), grid, levels=request_levels)
            return decode_request(sent), dataset.frames[made].poses[j]  # as the vehicle receives it

        others = sample.others
        if (
            early
        ):  # the collaborators' scans merged into the ego's (where the pose noise puts them), then the model alone
            key, noisy = (f, sample.ego.cav_id, inputs, tuple(a.cav_id for a in others)), bool(mu or sigma)
            ego = None if noisy else cache.get(key)  # a noisy merge is drawn anew each time, never kept
            if ego is None:
                placed = [
                    noisy_relative(sample.ego.world_from_lidar, a.world_from_lidar, mu, sigma, rng) for a in others
                ]
                merged = early_fused(
                    replace(sample, neighbour_from_ego=np.reshape(placed, (-1, 4, 4))),
                    model.cfg.grid,
                    lambda r: controlled(f, position[r.cav_id])["occupancy"],
                )
                ego = vehicles.vehicle(**to_batch(merged.ego.inputs, device))
                if not noisy:
                    cache[key] = ego
            others = []
        else:
            ego = vehicle(sample.ego.cav_id)
        # by default a request map reaches a neighbour a frame late, as in the graph: the ego's previous one (none on
        # a scenario's first frame: the neighbour then weighs by its own confidence alone)
        request = (
            request_made(f, sample.ego.cav_id)
            if not scans and codec is not None and codec.selection == "request"
            else None
        )
        union = request_answer == "union" and request is not None

        def union_wanted(record) -> np.ndarray | None:
            """The union of the requests of every other agent of the frame within comm range of `record`."""
            requests = {
                cav: r
                for cav in dataset.frames[f].cav_ids
                if cav != record.cav_id and (r := request_made(f, cav)) is not None
            }
            near = nearest_collaborators(record.world_from_lidar, {cav: r[1] for cav, r in requests.items()})
            asks = [request_for_neighbour(*requests[cav], record.world_from_lidar, grid) for cav in near]
            return union_request(asks) if asks else None

        candidates = {}
        for record in others:
            out = vehicle(record.cav_id)
            if codec is not None:
                key = (sample.key[:2], record.cav_id)
                if key not in senders:
                    senders[key] = SenderBudgets(codec)
                if (union or scans) and (f, record.cav_id) in broadcast:
                    out, size = broadcast[(f, record.cav_id)]
                elif scans:  # the same scan for every ego: sent once, for all
                    scan = controlled(f, position[record.cav_id])["occupancy"]
                    out, size = through_scan(model, scan, senders[key].config(None))
                    senders[key].spend(None, size)
                    broadcast[(f, record.cav_id)] = out, size
                elif union:
                    out, size = through_codec(model, out, senders[key].config(None), union_wanted(record))
                    senders[key].spend(None, size)
                    broadcast[(f, record.cav_id)] = out, size
                else:
                    wanted = None if request is None else request_for_neighbour(*request, record.world_from_lidar, grid)
                    out, size = through_codec(model, out, senders[key].config(sample.ego.cav_id), wanted)
                    senders[key].spend(sample.ego.cav_id, size)
                sent.append(size)
            candidates[record.cav_id] = (out, record.world_from_lidar)
        pred = predict_frame(
            model,
            ego,
            sample.ego.world_from_lidar,
            candidates,
            max_collaborators=len(candidates),
            mu=mu,
            sigma=sigma,
            rng=rng,
        )
        scenario = "/".join(sample.key[:2])
        confusions.setdefault(scenario, Confusion(model.cfg.num_classes)).add(pred.labels, sample.ego.labels)
        if labels is not None:
            labels[i] = pred.labels
        if later_frames is not None and previous_frame(f, sample.ego.cav_id) is not None:
            later_frames.setdefault(scenario, Confusion(model.cfg.num_classes)).add(pred.labels, sample.ego.labels)
        bar.update(1)
    bar.close()
    return confusions, float(np.mean(sent)) if sent else 0.0


def _plot(path: Path, x, series: dict[str, list[float]], xlabel: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, ys in series.items():
        ax.plot(x, [100 * y for y in ys], marker="o", label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("mIoU (%)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _write(out: Path, name: str, text: str, data: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.md").write_text(text + "\n")
    (out / f"{name}.json").write_text(json.dumps(data, indent=2) + "\n")
    print(text)


def _compare(
    opts,
    stem: str,
    heading: str,
    title: str,
    runs: dict[str, dict],
    reference: str,
    boot: Bootstrap,
    note: str = "",
    extra: dict | None = None,
) -> dict:
    """Writes runs (per-scenario confusions) as one table with intervals, plus each run's paired difference to
    `reference` (and a `note` below it, `extra` in the JSON)."""
    summaries = {name: boot.summary(c) for name, c in runs.items()}
    differences = {name: boot.difference(c, runs[reference]) for name, c in runs.items() if name != reference}
    text = (
        f"### {heading}: {title}\n\n"
        + markdown_table(summaries)
        + f"\n\nPaired differences (points), 95 % intervals over {len(boot.scenarios)} scenarios:\n\n"
        + difference_table(differences, reference)
        + (f"\n\n{note}" if note else "")
    )
    _write(
        opts.out,
        stem,
        text,
        {
            "title": title,
            "command": opts.command,
            "data": opts.data_origin,
            "trained": opts.trained,
            "reference": reference,
            **summaries,
            "differences": differences,
            **(extra or {}),
        },
    )
    return summaries


def _collaboration(opts, cfg, stem, title, measure, boot) -> None:
    runs = {"off": measure(collaborators=0, desc="collaboration off")[0], "on": measure(desc="collaboration on")[0]}
    _compare(opts, f"{stem}_collaboration", "Collaboration off / on", title, runs, "off", boot)


def _collaborators(opts, cfg, stem, title, measure, boot) -> None:
    counts = list(range(cfg.max_collaborators + 1))
    runs = {f"{n} collaborators": measure(collaborators=n, desc=f"{n} collaborators")[0] for n in counts}
    summaries = _compare(
        opts, f"{stem}_collaborators", "Number of collaborators (nearest first)", title, runs, "0 collaborators", boot
    )
    _plot(
        opts.out / f"{stem}_collaborators.png",
        counts,
        {c: [r[c]["miou"] for r in summaries.values()] for c in CONVENTIONS},
        "collaborators used",
        title,
    )


def _pose_noise(opts, cfg, stem, title, measure, boot) -> None:
    mus = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    runs = {f"mu={m:.1f}": measure(mu=m, sigma=0.02 if m else 0.0, desc=f"pose noise {m:.1f}")[0] for m in mus}
    summaries = _compare(
        opts, f"{stem}_pose_noise", "Pose noise (sigma 0.02 m, neighbours only)", title, runs, "mu=0.0", boot
    )
    _plot(
        opts.out / f"{stem}_pose_noise.png",
        mus,
        {c: [r[c]["miou"] for r in summaries.values()] for c in CONVENTIONS},
        "pose noise mean mu (m)",
        title,
    )


def _inputs(opts, cfg, stem, title, measure, boot) -> None:
    runs = {mode: measure(inputs=mode, desc=f"{mode} inputs")[0] for mode in INPUT_CONTROLS}
    _compare(
        opts,
        f"{stem}_inputs",
        "Input controls (real, blank and shuffled sensors of every agent)",
        title,
        runs,
        "real",
        boot,
    )


def _codec(opts, cfg, stem, title, measure, boot) -> None:
    """Bytes per neighbour-frame against mIoU and the share of the collaboration gain each codec keeps (gain: the
    lossless codec against no collaborator; kept: (codec - alone) / (lossless - alone), a paired interval each), over
    every sample and over the later frames (the ego there the frame before: a request map reaches them)."""
    rows = [
        "| feature codec | bytes per neighbour-frame | mIoU co3sop-readme | mIoU co3sop-code | mIoU surroundocc | "
        "Δ co3sop-code vs float32-dense-none | gain kept (%) [95 % interval] | gain kept after the first frame (%) |",
        "|---|---:|---:|---:|---:|---:|---|---|",
    ]
    alone_later: dict = {}
    alone = measure(collaborators=0, desc="no collaborator", later_frames=alone_later)[0]
    results, runs, later = {"alone": boot.summary(alone)}, {}, {}
    lossless = STANDARD_FEATURE_SETTINGS[0].name
    for setting in (*STANDARD_FEATURE_SETTINGS, *BUDGET_FEATURE_SETTINGS, *RANK_FEATURE_SETTINGS):
        later[setting.name] = {}
        runs[setting.name], size = measure(codec=setting, desc=setting.name, later_frames=later[setting.name])
        summary = boot.summary(runs[setting.name])
        diff = boot.difference(runs[setting.name], runs[lossless])["co3sop-code"]
        kept = boot.ratio(runs[setting.name], runs[lossless], alone)
        kept_later = boot.ratio(later[setting.name], later[lossless], alone_later)
        results[setting.name] = {
            "bytes": size,
            **summary,
            "difference": diff,
            "gain_kept": kept,
            "gain_kept_later_frames": kept_later,
        }
        rows.append(
            f"| {setting.name} | {size:,.0f} | {100 * summary['co3sop-readme']['miou']:.2f} | "
            f"{100 * summary['co3sop-code']['miou']:.2f} | {100 * summary['surroundocc']['miou']:.2f} | "
            f"{100 * diff['delta']:+.2f} [{100 * diff['ci95'][0]:.2f}, {100 * diff['ci95'][1]:.2f}] | "
            f"{100 * kept['ratio']:.0f} [{100 * kept['ci95'][0]:.0f}, {100 * kept['ci95'][1]:.0f}] | "
            f"{100 * kept_later['ratio']:.0f} [{100 * kept_later['ci95'][0]:.0f}, {100 * kept_later['ci95'][1]:.0f}] |"
        )
    text = (
        f"### Feature codecs over V2X: {title}\n\nAlone (no collaborator): mIoU co3sop-code "
        f"{100 * results['alone']['co3sop-code']['miou']:.2f}. Request maps are the ego's previous frame's, "
        f"moved by its "
        "motion (none on the ego's first frame of a scenario, where a vehicle weighs by its own confidence alone): the "
        "last column leaves those first frames out.\n\n" + "\n".join(rows)
    )
    _write(
        opts.out,
        f"{stem}_codec",
        text,
        {"title": title, "command": opts.command, "data": opts.data_origin, "trained": opts.trained, **results},
    )
    plot_codecs(opts.out / f"{stem}_codec.png", {name: r for name, r in results.items() if name != "alone"}, title)


# What the papers' collaborators send per neighbour-frame: the curve is read against them
PAPER_SIZES = {"Co3SOP (dense float32)": 18.9e6, "CoHFF": 0.78e6, "VOGS-CP": 0.27e6}
# the V2X goal: 90 % of the collaboration gain in this many bytes per neighbour-frame (one shared 6 Mbit/s channel)
GOAL_BYTES = 8192


def plot_codecs(path: Path, results: dict[str, dict], title: str) -> None:
    """Share of the collaboration gain kept against bytes per neighbour-frame (log scale), with intervals: results[codec
    name] = {"bytes": ..., "gain_kept": {"ratio": ..., "ci95": (low, high)}}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9.5, 4.5))
    colours = plt.get_cmap(
        "tab20"
    ).colors  # one per codec (the default cycle repeats after 10; int4's own marker after 20)
    for i, (name, r) in enumerate(results.items()):
        low, high = r["gain_kept"]["ci95"]
        kept = r["gain_kept"]["ratio"]
        marker = "D" if name.startswith("int4") else "s" if "request" in name else "o"
        ax.errorbar(
            r["bytes"],
            100 * kept,
            yerr=[[100 * (kept - low)], [100 * (high - kept)]],
            fmt=marker,
            capsize=3,
            label=name,
            color=colours[i % len(colours)],
            markerfacecolor="none" if "pca" in name else None,
        )
    for name, size in PAPER_SIZES.items():
        ax.axvline(size, color="grey", linestyle=":", linewidth=1)
        ax.text(size, ax.get_ylim()[1], name, rotation=90, va="top", ha="right", fontsize=7, color="grey")
    ax.axvline(
        GOAL_BYTES,
        color="red",
        linestyle="--",
        linewidth=0.8,
        alpha=0.5,
        zorder=0,
        label=f"goal: {GOAL_BYTES // 1024} KB",
    )
    ax.axhline(90, color="red", linestyle=":", linewidth=0.8, zorder=0, label="goal: 90 % of the gain")
    ax.set_xscale("log")
    ax.set_xlabel("bytes per neighbour-frame")
    ax.set_ylabel("collaboration gain kept (%)")
    ax.set_title(textwrap.fill(title, 120), fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the axes: no point hidden
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")  # the legend beside the axes included
    plt.close(fig)


def nearest_distance(sample: Sample) -> float:
    """Ground distance (m) from the ego to its nearest collaborator in communication range; inf without one."""
    if not sample.others:
        return math.inf
    return float(np.hypot(*(sample.others[0].world_from_lidar[:2, 3] - sample.ego.world_from_lidar[:2, 3])))


DISTANCE_BINS: dict[str, Callable[[float], bool]] = {
    "under 20 m": lambda d: d < 20.0,
    "20-40 m": lambda d: 20.0 <= d < 40.0,
    f"40-{COMM_RANGE:.0f} m": lambda d: 40.0 <= d <= COMM_RANGE,
    f"none within {COMM_RANGE:.0f} m": math.isinf,
}


def _distance(opts, cfg, stem, title, measure, boot) -> None:
    """Off / on per bin of the nearest collaborator's distance, each bin over the test scenarios that have samples
    in it."""
    results = {}
    for name, accept in DISTANCE_BINS.items():

        def where(sample, accept=accept):
            return accept(nearest_distance(sample))

        off = measure(collaborators=0, where=where, desc=f"{name}: off")[0]
        if off:
            on = measure(where=where, desc=f"{name}: on")[0]
            binned = Bootstrap(list(off), seed=opts.seed)
            results[name] = {
                "samples": sum(c.frames for c in off.values()),
                "off": binned.summary(off),
                "on": binned.summary(on),
                "difference": binned.difference(on, off),
            }
    text = f"### Collaboration gain by the nearest collaborator's distance: {title}\n\n" + "\n".join(
        distance_table(results)
    )
    _write(
        opts.out,
        f"{stem}_distance",
        text,
        {"title": title, "command": opts.command, "data": opts.data_origin, "trained": opts.trained, "bins": results},
    )


def distance_table(bins: dict) -> list[str]:
    """The rows of the distance ablation from its JSON `bins` (report prints the same table)."""

    def delta(d: dict) -> str:
        return f"{100 * d['delta']:+.2f} [{100 * d['ci95'][0]:.2f}, {100 * d['ci95'][1]:.2f}]"

    rows = [
        "| nearest collaborator | samples | scenarios | off mIoU 1..23 | on mIoU 1..23 | Δ mIoU 1..23 [95 %] "
        "| Δ geometry IoU [95 %] |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in bins.items():
        rows.append(
            f"| {name} | {r['samples']} | {r['off']['scenarios']} | {100 * point(r['off'], 'co3sop-code'):.2f} | "
            f"{100 * point(r['on'], 'co3sop-code'):.2f} | {delta(r['difference']['co3sop-code'])} | "
            f"{delta(r['difference']['geometry'])} |"
        )
    return rows


def _precision(opts, cfg, stem, title, measure, boot) -> None:
    """--precision (reduced; with --vehicle-precision, the ego's, and that the vehicle halves') against float32 on
    the same device: the paired mIoU difference and the share of voxels whose label is the same."""
    fast, vehicles = opts.inference, opts.vehicle_inference or opts.inference
    if not (fast.reduced or vehicles.reduced):
        raise Co3sopError(
            "--ablation precision compares --precision bfloat16, float16 or int8 with float32: name one of them"
        )
    reference = replace(fast, precision="float32")
    name = fast.precision if vehicles == fast else f"{fast.precision} (vehicle halves {vehicles.precision})"
    labels: dict[str, dict] = {}
    runs = {}
    for run, path, vehicle_path in (("float32", reference, reference), (name, fast, vehicles)):  # own paths last
        if opts.vehicles is not None:
            opts.vehicles.use(vehicle_path)
        labels[run] = {}
        runs[run] = measure(path=path, shared={}, labels=labels[run], desc=run)[0]
    same = sum(int((labels["float32"][i] == labels[name][i]).sum()) for i in labels["float32"])
    total = sum(v.size for v in labels["float32"].values())
    agreement = same / max(1, total)
    _compare(
        opts,
        f"{stem}_precision",
        f"Inference precision ({fast.device})",
        title,
        runs,
        "float32",
        boot,
        f"Labels equal to float32's on {100 * agreement:.2f} % of {total} voxels ({len(labels['float32'])} samples).",
        {
            "device": fast.device,
            # what the reduced path ran on and computed in: its rows differ from one CPU to another
            **({"hardware": cpu_units()} if fast.torch_device.type == "cpu" else {}),
            **({"floats": fast.floats} if fast.int8 else {}),
            "label_agreement": agreement,
            "voxels": total,
        },
    )


ABLATIONS = {
    "collaboration": _collaboration,
    "collaborators": _collaborators,
    "pose-noise": _pose_noise,
    "codec": _codec,
    "inputs": _inputs,
    "distance": _distance,
    "precision": _precision,
}


def evaluate_models(opts) -> int:
    """Every model of `opts` (evaluate's options) on its splits, or its ablations; tables written under opts.out."""
    torch.set_num_threads(opts.threads)
    opts.data_origin = data_origin(opts.data)
    opts.inference = inference_path(opts.device, opts.precision, compiled=not opts.reference_paths, what="--")
    if opts.vehicle_precision == "int8" and opts.inference.torch_device.type != "cpu":
        raise Co3sopError(f"--vehicle-precision int8 with --device {opts.inference.device}: int8 runs on the CPU only")
    table: dict[str, dict] = {}
    for path in [resolve_checkpoint(m, "--model") for m in opts.model] if opts.model else [shipped_checkpoint()]:
        model, checkpoint = load_model(path)
        opts.trained = checkpoint.get("meta", checkpoint).get(
            "history", []
        )  # the train commands behind the weights, in the JSON
        # the ego's path, as an ego node takes its precision (auto: int8 where its head is tuned for it)
        opts.inference = model.ego_path(opts.device, opts.precision, compiled=not opts.reference_paths, what="--")
        model.use(opts.inference)
        if opts.inference.int8 and not model.path.int8:
            raise Co3sopError(f"--precision int8: {path}: {model.int8_missing()}")
        # the vehicle halves' path, as a vehicle node takes its precision (auto: int8 where they are tuned for it)
        own = opts.vehicle_precision is not None
        vehicles = model.vehicle_path(
            opts.inference.device,
            opts.vehicle_precision if own else opts.precision,
            compiled=not opts.reference_paths,
            what="--vehicle-" if own else "--",
        )
        opts.vehicle_inference = vehicles if vehicles != opts.inference else None
        opts.vehicles = None
        if opts.vehicle_inference is not None:  # the vehicle halves on a path of their own: a copy of the model
            opts.vehicles = load_model(path)[0].use(opts.vehicle_inference)
            if opts.vehicle_precision == "int8" and not opts.vehicles.path.int8:  # asked for, not taken by auto
                raise Co3sopError(f"--vehicle-precision int8: {path}: {opts.vehicles.int8_missing()}")
        cfg = model.cfg
        dataset = OccupancyDataset(opts.data, opts.splits, cfg, cache=opts.cache)
        title = f"{cfg.name} ({cfg.modality}), {cfg.range}, {'+'.join(opts.splits)}: {len(dataset)} samples"
        shared = vehicle_cache()

        boot = Bootstrap(["/".join(k) for k in dataset.scenarios], seed=opts.seed)

        def measure(model=model, dataset=dataset, shared=shared, **kw) -> tuple[dict, float]:
            return evaluate(
                model, dataset, cache=shared, seed=opts.seed, vehicles=opts.vehicles, **kw
            )  # runs of one model share vehicle outputs

        if not opts.ablation:
            label = f"{cfg.name} {cfg.range}" + (
                "" if opts.collaborators is None else f", {opts.collaborators} collaborators"
            )
            if label in table:  # two runs of one preset: tell the columns apart by run folder
                label += f" ({path.parent.name})"
            table[label] = {
                **boot.summary(measure(collaborators=opts.collaborators, desc=label)[0]),
                "model": str(path),
                "trained": opts.trained,
            }
        for ablation in opts.ablation:
            ABLATIONS[ablation](opts, cfg, f"{cfg.name}_{cfg.range}", title, measure, boot)
    if table:
        splits = "+".join(opts.splits)
        _write(
            opts.out,
            "evaluation",
            f"### Per-class IoU (%) and mIoU on {splits} (95 % intervals over scenarios)\n\n" + markdown_table(table),
            {"splits": opts.splits, "command": opts.command, "data": opts.data_origin, **table},
        )
    return 0
