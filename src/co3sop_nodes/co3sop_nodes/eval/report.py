"""The benchmark page (markdown) from `evaluate`'s JSON, so no figure is ever typed by hand (the `report`
command, co3sop_nodes.cli.report, explains its sections)."""

from __future__ import annotations

import json
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.common.grid import BENCHMARK_RANGES
from co3sop_nodes.eval.codec_comparison import comparison_table
from co3sop_nodes.eval.evaluate import distance_table
from co3sop_nodes.eval.metrics import SCORES, Bootstrap, confusions_of, markdown_table, point
from co3sop_nodes.eval.observed import observed_table
from co3sop_nodes.model.config import preset as model_preset
from co3sop_nodes.v2x.neighbours import COMM_RANGE

# a run's folder: <preset>-<range>-s<seed>, and -<tag> for a second recipe of the same run (run_protocol.sh's TAG)
RUN_NAME = re.compile(r"(?P<preset>.+)-(?P<range>\d+\.\dm)-s(?P<seed>\d+)(?:-(?P<tag>[A-Za-z0-9]+))?")
SCORE_NAMES = {
    "co3sop-code": "mIoU 1..23 (Co3SOP code)",
    "co3sop-readme": "mIoU 24 classes (Co3SOP README)",
    "surroundocc": "mIoU present classes (SurroundOcc)",
    "geometry": "geometry IoU",
}


def pct(value: float) -> str:
    return f"{100 * value:.2f}"


def span(low_high: list[float]) -> str:
    return f"[{pct(low_high[0])}, {pct(low_high[1])}]"


# what the page reads from each JSON it is given, so a damaged or foreign file is named, never a traceback
SUMMARY = ("frames", "per_class_iou", *(s for s in SCORES if s != "geometry"), "ci95", "per_scenario")
ABLATION = ("title", "reference", "differences")  # any ablation (inputs, collaborators, pose_noise)
NEEDS = {
    "collaboration": (*ABLATION, "off", "on"),
    "evaluation": (),
    "distance": ("title", "command", "bins"),
    "precision": (*ABLATION, "command", "float32", "device", "label_agreement", "voxels"),
    "observed": ("splits", "range", "samples", "all", "classes"),
    "learned codec": ("title", "runs"),
}
# beside the scored runs
META = {
    "data",
    "title",
    "command",
    "trained",
    "reference",
    "differences",
    "splits",
    "device",
    "hardware",
    "floats",
    "label_agreement",
    "voxels",
}


def _missing_runs(runs: dict) -> list[str]:
    """Scored runs (Bootstrap summaries) lacking a field this page reads."""
    if not runs:
        return ["a scored run"]
    return [
        name if not isinstance(r, dict) else f"{name}.{k}"
        for name, r in runs.items()
        for k in SUMMARY
        if not isinstance(r, dict) or k not in r
    ][:5]


def _missing_gains(gains: object, where: str) -> list[str]:
    """Paired differences ({name: {score: {delta, ci95}}}) lacking the mIoU 1..23 this page prints."""
    if not isinstance(gains, dict):
        return [where]
    return [
        f"{where}.{name}.co3sop-code"
        for name, d in gains.items()
        if not (
            isinstance(d, dict)
            and isinstance(d.get("co3sop-code"), dict)
            and {"delta", "ci95"} <= d["co3sop-code"].keys()
        )
    ]


def read_json(path: Path, kind: str) -> dict:
    """`evaluate`'s (or observed.py's, or bench_learned_codec.py's) JSON of one kind at `path`, checked for the fields
    this page reads."""
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise Co3sopError(f"{path}: not JSON ({exc})") from None
    if not isinstance(data, dict):
        raise Co3sopError(f"{path}: not {kind} JSON (a JSON {type(data).__name__}, not an object)")
    missing = [k for k in NEEDS.get(kind, ABLATION) if k not in data]
    if not missing and kind == "distance":
        bins = data["bins"] if isinstance(data["bins"], dict) else {}
        missing += _missing_runs(
            {
                f"bins.{b}.{side}": v.get(side) if isinstance(v, dict) else None
                for b, v in bins.items()
                for side in ("off", "on")
            }
        )
        missing += _missing_gains(
            {f"{b}.difference": v.get("difference") if isinstance(v, dict) else None for b, v in bins.items()}, "bins"
        )
    elif not missing and kind not in ("observed", "learned codec"):  # theirs: a table each, checked where it's made
        runs = {k: v for k, v in data.items() if k not in META}
        missing += _missing_runs(runs)
        if kind != "evaluation":
            missing += [] if data["reference"] in runs else [f"the reference run {data['reference']!r}"]
            missing += _missing_gains(data["differences"], "differences")
        if kind == "collaboration" and "on" not in data["differences"]:
            missing.append("differences.on")
    if missing:
        raise Co3sopError(f"{path}: not {kind} JSON as evaluate writes it: no " + ", ".join(missing))
    return data


def _load(folder: Path, kind: str) -> dict | None:
    found = sorted(folder.glob(f"*_{kind}.json"))
    return read_json(found[0], kind) if found else None


def recipe(report: dict) -> str:
    """The training steps per stage behind an evaluation (from the train commands its JSON records)."""
    steps: dict[str, int] = {}
    for trained in report.get("trained", []):
        steps[trained["stage"]] = trained["steps"]  # a resumed or extended run: its last command's total
    return " + ".join(f"{stage} {n}" for stage, n in steps.items()) + " steps" if steps else "steps not recorded"


def collect(results: Path) -> dict[tuple[str, str, str], dict[int, Path]]:
    """{(preset, range, recipe): {seed: folder}} of every run folder under `results`: seeds trained with
    different step counts are never pooled."""
    runs: dict[tuple[str, str, str], dict[int, Path]] = {}
    for folder in sorted(p for p in results.iterdir() if p.is_dir()):
        m = RUN_NAME.fullmatch(folder.name)
        report = _load(folder, "collaboration")
        if m and report:
            runs.setdefault((m["preset"], m["range"], recipe(report)), {})[int(m["seed"])] = folder
    if not runs:
        raise Co3sopError(f"{results}: no <preset>-<range>-s<seed> folder with evaluate's collaboration JSON")
    return runs


def scored_alone(folder: Path, name: str) -> tuple[dict, dict] | None:
    """A model of the run scored alone (`evaluate` with 0 collaborators into folder/`name`: "ego-stage" for a
    collaborative run's ego stage, "alone" for a single-agent model), if evaluated: the evaluation JSON and its
    scores."""
    path = folder / name / "evaluation.json"
    if not path.is_file():
        return None
    made = read_json(path, "evaluation")
    return made, next(v for k, v in made.items() if k not in META)


def single_agent_runs(results: Path) -> Iterator[tuple[Path, re.Match, dict, dict]]:
    """(folder, its name's match, evaluation JSON, scores) of every single-agent run under `results` scored alone."""
    for folder in sorted(p for p in results.iterdir() if p.is_dir()):
        m = RUN_NAME.fullmatch(folder.name)
        scored = scored_alone(folder, "alone") if m else None
        if scored is not None:
            yield folder, m, *scored


def mean_sd(x: np.ndarray) -> str:
    return pct(x.mean()) + (f" ± {100 * x.std(ddof=1):.2f}" if len(x) > 1 else "")


def headline(runs: dict[tuple[str, str, str], dict[int, Path]]) -> list[str]:
    lines = [
        "| model | range | training steps | seeds | ego stage alone | off (fusion model, no collaborator) | "
        "on | gain on - off | "
        "gain on - off, per seed [95 % interval] | gain on - ego stage, per seed [95 % interval] | geometry "
        "IoU off / on |",
        "|---|---|---|---:|---:|---:|---:|---:|---|---|---:|",
    ]
    for (preset, rng, steps), seeds in runs.items():
        reports = [_load(f, "collaboration") for f in seeds.values()]
        off = np.array([point(r["off"], "co3sop-code") for r in reports])
        on = np.array([point(r["on"], "co3sop-code") for r in reports])
        gains = [r["differences"]["on"]["co3sop-code"] for r in reports]
        geo = [(point(r["off"], "geometry"), point(r["on"], "geometry")) for r in reports]
        alone, over_alone = [], []
        for folder, r in zip(seeds.values(), reports):
            scored = scored_alone(folder, "ego-stage")
            if scored is not None:
                single = scored[1]
                alone.append(point(single, "co3sop-code"))
                boot = Bootstrap(list(r["on"]["per_scenario"]))
                over_alone.append(boot.difference(confusions_of(r["on"]), confusions_of(single))["co3sop-code"])
        lines.append(
            f"| {preset} | {rng} | {steps} | {len(seeds)} | {mean_sd(np.array(alone)) if alone else '-'} | "
            f"{mean_sd(off)} | {mean_sd(on)} | "
            f"**{mean_sd(on - off)}** | "
            + ", ".join(f"{pct(g['delta'])} {span(g['ci95'])}" for g in gains)
            + " | "
            + (", ".join(f"{pct(g['delta'])} {span(g['ci95'])}" for g in over_alone) or "-")
            + f" | {pct(np.mean([g[0] for g in geo]))} / {pct(np.mean([g[1] for g in geo]))} |"
        )
    return lines


# the project's goal: a collaborative LiDAR gain of at least +3 mIoU points (1..23), every interval above zero
@dataclass(frozen=True)
class Goals:
    """What the page sets each model against (a protocol's `goals` section, e.g. config/benchmark.yaml)."""

    lidar_gain: float  # the LiDAR models' mean collaboration gain (fraction: 0.03 = 3 points) ...
    lidar_gain_ranges: tuple[str, ...]  # ... at these ranges
    camera_miou: float  # the camera models' mIoU (1..23, with collaboration) at 51.2 m
    headline_range: str  # a headline model at this range ...
    headline_seeds: int  # ... is trained with at least this many seeds


def read_goals(path: Path) -> Goals:
    """The `goals` section of a protocol recipe (YAML), in points as written there; a missing or wrong field named."""
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise Co3sopError(f"{path}: not a readable YAML recipe ({exc})") from None
    section = data.get("goals") if isinstance(data, dict) else None
    try:
        return Goals(
            lidar_gain=float(section["lidar_gain"]["points"]) / 100,
            lidar_gain_ranges=tuple(str(r) for r in section["lidar_gain"]["ranges"]),
            camera_miou=float(section["camera_miou"]["points"]) / 100,
            headline_range=str(section["headline"]["range"]),
            headline_seeds=int(section["headline"]["seeds"]),
        )
    except (TypeError, KeyError, ValueError) as exc:
        raise Co3sopError(
            f"{path}: 'goals' needs lidar_gain {{points, ranges}}, camera_miou {{points}}, headline {{range, seeds}} "
            f"(missing or wrong: {exc})"
        ) from None


def goals(runs: dict[tuple[str, str, str], dict[int, Path]], results: Path, target: Goals) -> list[str]:
    """Per model and range, against its goal: the LiDAR model's mean gain (at the goal's ranges), the camera model's
    mIoU at 51.2 m; and whether every seed's gain interval excludes zero. A goal reached at the headline range with
    fewer seeds than a headline model needs is met on those seeds only, and says so. A LiDAR gain short of its goal,
    or at a range without one, is set against what the collaborators' LiDAR adds there (observed-<range>.json), where
    it was measured."""
    lines = []
    for (name, rng, steps), seeds in runs.items():
        if model_preset(name).early_fusion:  # a reference for the LiDAR model's gain, with no goal of its own
            continue
        reports = [_load(f, "collaboration") for f in seeds.values()]
        gains = [r["differences"]["on"]["co3sop-code"] for r in reports]
        mean = float(np.mean([g["delta"] for g in gains]))
        above = all(g["ci95"][0] > 0 for g in gains)
        about = f"- {name}, {rng}, {steps} ({len(seeds)} seed{'s' * (len(seeds) > 1)}): "
        intervals = f"every seed's gain interval above zero: {'yes' if above else 'no'}"
        if model_preset(name).modality == "camera":
            if rng != "51.2m":
                continue
            score, goal, what = (
                float(np.mean([point(r["on"], "co3sop-code") for r in reports])),
                target.camera_miou,
                "mIoU 1..23 with collaboration",
            )
        elif rng not in target.lidar_gain_ranges:
            lines.append(
                about + f"mean gain {pct(mean)}; {intervals}; no goal at this range "
                f"(the project sets +{pct(target.lidar_gain)} at "
                f"{' and '.join(target.lidar_gain_ranges)})."
                + why_short(results / f"observed-{rng}.json")
                + early_reference(runs, rng)
            )
            continue
        else:
            score, goal, what = mean, target.lidar_gain, "mean gain"
        verdict = (
            ("met" if above else "not met: an interval reaches zero")
            if score >= goal
            else f"not met: short by {pct(goal - score)} points"
        )
        if verdict == "met" and rng == target.headline_range and len(seeds) < target.headline_seeds:
            verdict = (
                f"met on {len(seeds)} seed{'s' * (len(seeds) > 1)}; a headline model at {rng} needs "
                f"{target.headline_seeds}"
            )
        lines.append(
            about
            + f"{what} {pct(score)} against the goal of {'+' * (what == 'mean gain')}{pct(goal)}"
            + ("" if what == "mean gain" else f" (gain {pct(mean)})")
            + f"; {intervals}; **{verdict}**."
            + (
                why_short(results / f"observed-{rng}.json") + early_reference(runs, rng)
                if what == "mean gain" and score < goal
                else ""
            )
        )
    return lines


def early_reference(runs: dict[tuple[str, str, str], dict[int, Path]], rng: str) -> str:
    """What the early-fusion reference at `rng` gains, where it was run: the same neighbours' information merged
    as scans before one network, instead of shared as features."""
    found = [(name, seeds) for (name, r, _), seeds in runs.items() if r == rng and model_preset(name).early_fusion]
    return "".join(
        f" Early fusion ({name}: the collaborators' scans merged into the ego's before the same SSCNet-style "
        f"network) gains "
        + ", ".join(
            f"{pct(g['delta'])} {span(g['ci95'])} (seed {seed})"
            for seed, g in (
                (seed, _load(f, "collaboration")["differences"]["on"]["co3sop-code"]) for seed, f in seeds.items()
            )
        )
        + " over its own scan alone."
        for name, seeds in found
    )


def why_short(observed: Path) -> str:
    """What bounds a LiDAR gain: the share of occupied voxels the collaborators' returns add to the ego's."""
    if not observed.is_file():
        return ""
    data = read_json(observed, "observed")
    seen, classes = data["all"], data["classes"]
    added = {name: c["ego+collaborators"] - c["ego"] for name, c in classes.items()}
    top = sorted(added, key=lambda n: -added[n] * classes[n]["voxels"])[:3]  # most voxels added
    return (
        f" Why: on these test samples the collaborators' LiDAR returns raise the share of occupied voxels hit by"
        f" {pct(seen['ego+collaborators'] - seen['ego'])} points only ({pct(seen['ego'])} % -> "
        f"{pct(seen['ego+collaborators'])} %; "
        + ", ".join(f"{n} +{pct(added[n])} points" for n in top)
        + '): what fusion can add beyond inference is bounded by that ("What the neighbours can see" below).'
    )


# The paper's Table 2 mIoU at 25.6 / 51.2 / 76.8 m (on its CARLA data: a reference for the methods' order, not their
# level)
PAPER_TABLE2 = {
    "SSCNet": (13.21, 9.58, 10.04),
    "LMSCNet": (24.92, 20.35, 17.62),
    "OccFormer": (29.48, 25.41, 24.12),
    "SurroundOcc": (28.71, 25.76, 24.68),
    "Co3SOP-Base": (30.04, 27.50, 27.00),
}


def method(name: str) -> str:
    """The paper's name for the method a preset builds (its Table 2 columns)."""
    cfg = model_preset(name)
    if cfg.fusion:
        return "Co3SOP-Base" + (" (LiDAR)" if cfg.modality == "lidar" else "")
    if cfg.early_fusion:
        return "Early fusion (LiDAR)"
    if cfg.modality == "lidar":
        return {"sscnet": "SSCNet", "lmscnet": "LMSCNet"}[cfg.lidar.kind]
    return "OccFormer" if cfg.head == "occformer" else "SurroundOcc"


def table2_section(results: Path, runs: dict[tuple[str, str, str], dict[int, Path]]) -> list[str]:
    """The paper's Table 2 in its layout: every method at the three ranges, mIoU 1..23 on `test` (single-agent
    models alone, collaborative ones with their collaborators), one seed with its interval, several as mean ± sd."""
    cells: dict[str, dict[str, list[str]]] = {}
    recipes = Counter((name, rng) for name, rng, _ in runs)  # a cell with several recipes names each one's steps
    for (name, rng, steps), seeds in runs.items():
        on = {seed: _load(f, "collaboration")["on"] for seed, f in seeds.items()}
        if len(on) > 1:
            value, who = mean_sd(np.array([point(r, "co3sop-code") for r in on.values()])), f"{len(on)} seeds"
        else:
            ((seed, r),) = on.items()
            value, who = f"{pct(point(r, 'co3sop-code'))} {span(r['ci95']['co3sop-code'])}", f"seed {seed}"
        cells.setdefault(name, {}).setdefault(rng, []).append(
            f"{value} ({who}{', ' + steps if recipes[name, rng] > 1 else ''})"
        )
    for _, m, _, alone in single_agent_runs(results):
        cells.setdefault(m["preset"], {}).setdefault(m["range"], []).append(
            f"{pct(point(alone, 'co3sop-code'))} {span(alone['ci95']['co3sop-code'])} (seed {m['seed']})"
        )
    order = [*PAPER_TABLE2, "Co3SOP-Base (LiDAR)", "Early fusion (LiDAR)"]
    rows = []
    for name in sorted(cells, key=lambda n: (order.index(method(n)), n)):
        paper = PAPER_TABLE2.get(method(name))
        rows.append(
            f"| {method(name)} | {name} | {model_preset(name).modality} | "
            + " | ".join("; ".join(cells[name].get(rng, [])) or "-" for rng in BENCHMARK_RANGES)
            + f" | {' / '.join(f'{v:.2f}' for v in paper) if paper else '-'} |"
        )
    return [
        "## Table 2: every method at the three ranges (mIoU 1..23, %, test)",
        "",
        "The paper's Table 2 in its layout, from the runs on this page: single-agent models scored alone,",
        "Co3SOP-Base and early fusion with their collaborators; one seed with its 95 % interval, several as mean ±",
        "sd over seeds.",
        "The paper's figures are on its CARLA data with its models' full sizes: compare the order of the",
        "methods, not their level. `-`: not run under the protocol yet.",
        "",
        "| method | preset | modality | " + " | ".join(BENCHMARK_RANGES) + " | the paper (25.6 / 51.2 / 76.8 m) |",
        "|---|---|---|" + "---:|" * len(BENCHMARK_RANGES) + "---:|",
        *rows,
        "",
    ]


# The paper's pose-noise table (Co3SOP-Base, camera): mIoU at 25.6 / 51.2 / 76.8 m for each mean offset (sigma 0.02 m)
PAPER_POSE_NOISE = {
    "mu=0.0": (30.04, 27.50, 27.00),
    "mu=0.1": (29.95, 27.38, 26.96),
    "mu=0.2": (29.78, 27.13, 26.83),
    "mu=0.3": (29.59, 26.82, 26.64),
    "mu=0.4": (29.41, 26.50, 26.39),
    "mu=0.5": (29.30, 26.20, 26.15),
}


def across_ranges(
    runs: dict[tuple[str, str, str], dict[int, Path]], kind: str, what: str, said: str, paper: dict | None = None
) -> list[str]:
    """One ablation (`kind`: pose_noise, collaborators) in the paper's layout, a row per setting and a column per
    range, for each model and recipe that ran it (its first seed): mIoU 1..23 with the paired difference to the
    ablation's reference and its interval; `said`: what the paper reports of it; `paper`, where given, its
    figures per setting."""
    found: dict[tuple[str, str], dict[str, dict]] = {}
    seeds_of: dict[tuple[str, str], set[int]] = {}
    for (name, rng, steps), seeds in runs.items():
        report = _load(seeds[min(seeds)], kind)
        if report:
            found.setdefault((name, steps), {})[rng] = report
            seeds_of.setdefault((name, steps), set()).add(min(seeds))
    out = []
    for (name, steps), by_range in found.items():
        settings = list(
            dict.fromkeys(k for r in by_range.values() for k, v in r.items() if isinstance(v, dict) and "ci95" in v)
        )
        head = (
            "| setting | " + " | ".join(BENCHMARK_RANGES) + (" | the paper (25.6 / 51.2 / 76.8 m) |" if paper else " |")
        )
        rows = [head, "|---|" + "---:|" * (len(BENCHMARK_RANGES) + bool(paper))]
        for setting in settings:
            cells = []
            for rng in BENCHMARK_RANGES:
                r = by_range.get(rng, {})
                if setting not in r:
                    cells.append("-")
                    continue
                d = r["differences"].get(setting)
                cells.append(
                    pct(point(r[setting], "co3sop-code"))
                    + (f" ({pct(d['co3sop-code']['delta'])} {span(d['co3sop-code']['ci95'])})" if d else "")
                )
            rows.append(
                f"| {setting} | "
                + " | ".join(cells)
                + (
                    f" | {' / '.join(f'{v:.2f}' for v in paper[setting]) if setting in paper else '-'} |"
                    if paper
                    else " |"
                )
            )
        out += [f"### {name}, {steps} (seed {', '.join(map(str, sorted(seeds_of[name, steps])))})", "", *rows, ""]
    if not out:
        return []
    return [
        f"## {what} at the three ranges (mIoU 1..23, %, test)",
        "",
        "The paper's layout: one column per range, the first seed of each model and recipe; in brackets the paired",
        "difference to the first row with its 95 % interval. `-`: not evaluated at that range. Each run's table",
        "below gives every score and the command that made it.",
        said,
        "",
        *out,
    ]


def single_agent_section(results: Path) -> list[str]:
    """The single-agent models (the paper's Table 2 baselines: no fusion) scored alone, one row per run, with the
    input controls of their first seed."""
    rows, controls = [], []
    for folder, m, made, alone in single_agent_runs(results):
        rows.append(
            f"| {m['preset']} | {m['range']} | {recipe(alone)} | {m['seed']} | "
            + " | ".join(f"{pct(point(alone, s))} {span(alone['ci95'][s])}" for s in SCORES)
            + f" | `{made.get('command', '')}` |"
        )
        controls += compact(_load(folder, "inputs"), f"Input controls: {folder.name}")
    if not rows:
        return []
    return [
        "## Single-agent models (the paper's Table 2 baselines)",
        "",
        "Models without fusion, trained in one stage on single agents and scored alone on `test`, each score with its",
        "95 % interval over test scenarios (`ros2_ws/run_protocol.sh` with the preset in PRESETS).",
        "",
        "| model | range | training steps | seed | " + " | ".join(SCORE_NAMES[s] for s in SCORES) + " | command |",
        "|---|---|---|---:|" + "---:|" * len(SCORES) + "---|",
        *rows,
        "",
        *controls,
    ]


def compact(report: dict | None, title: str) -> list[str]:
    """One row per run of an ablation: each score with its interval, and the paired difference in mIoU 1..23."""
    if report is None:
        return []
    runs = {k: v for k, v in report.items() if isinstance(v, dict) and "ci95" in v}
    made = [f"Made by `{report['command']}`.", ""] if "command" in report else []
    lines = [
        f"#### {title}",
        "",
        report["title"],
        "",
        *made,
        "| run | " + " | ".join(SCORE_NAMES[s] for s in SCORES) + f" | Δ mIoU 1..23 vs {report['reference']} |",
        "|---|" + "---:|" * (len(SCORES) + 1),
    ]
    for name, r in runs.items():
        d = report["differences"].get(name)
        delta = f"{pct(d['co3sop-code']['delta'])} {span(d['co3sop-code']['ci95'])}" if d else "reference"
        lines.append(
            f"| {name} | " + " | ".join(f"{pct(point(r, s))} {span(r['ci95'][s])}" for s in SCORES) + f" | {delta} |"
        )
    return lines + [""]


def observed_section(results: Path) -> list[str]:
    """The tables of ros2_ws/benchmarks/observed.py (its --out JSON, observed-<range>.json beside the runs)."""
    found = sorted(results.glob("observed-*.json"))
    if not found:
        return []
    out = [
        "## What the neighbours can see",
        "",
        "Share of occupied ground-truth voxels (classes 1..23) that a LiDAR return falls in: the ego's alone,",
        "and the ego's with its collaborators' (`ros2_ws/benchmarks/observed.py --data data/bench --splits test",
        "--range R --out .../observed-R.json`). Fusion can only add what the neighbours see and the ego does not,",
        "and what a model infers around it; building interiors are occupied but seen by no one.",
        "",
    ]
    for path in found:
        data = read_json(path, "observed")
        out += [observed_table(data, f"{'+'.join(data['splits'])}, {data['range']}"), ""]
    return out


def validate_section(results: Path) -> list[str]:
    """Choices made on `validate` (RESULTS/validate/<choice>/, evaluate's collaboration JSON per option)."""
    found = sorted((results / "validate").glob("*/*_collaboration.json"))
    if not found:
        return []
    out = [
        "## Choices made on validate",
        "",
        "Each option of a recipe choice evaluated on the `validate` split (never `test`); the protocol uses the",
        "option its settings name (`ros2_ws/run_protocol.sh`).",
        "",
        "| option | model | training steps | off | on | gain on - off [95 % interval] | command |",
        "|---|---|---|---:|---:|---|---|",
    ]
    for path in found:
        r = read_json(path, "collaboration")
        gain = r["differences"]["on"]["co3sop-code"]
        model = " ".join(path.stem.split("_")[:2])  # evaluate names its JSON <preset>_<range>_<ablation>
        out.append(
            f"| {path.parent.name} | {model} | {recipe(r)} | {pct(point(r['off'], 'co3sop-code'))} | "
            f"{pct(point(r['on'], 'co3sop-code'))} | "
            f"{pct(gain['delta'])} {span(gain['ci95'])} | `{r.get('command', '')}` |"
        )
    return out + [""]


def _comparisons(results: Path, pattern: str, intro: list[str]) -> list[str]:
    """`intro`, then the table of each bench_learned_codec.py --out JSON RESULTS/codec/`pattern` (none: nothing)."""
    found = sorted((results / "codec").glob(pattern))
    if not found:
        return []
    out = list(intro)
    for path in found:
        out += [*comparison_table(read_json(path, "learned codec")), ""]
    return out


def wire_code_section(results: Path) -> list[str]:
    """Learned wire codes against the transform codec on `test` (RESULTS/codec/learned-<range>-test.json)."""
    return _comparisons(
        results,
        "learned-*-test.json",
        [
            "## A code learned for the V2X wire against the transform codec",
            "",
            "The same byte budgets per neighbour-frame under request maps; both scored against the model the code was",
            "trained from (`--reference`), alone and with lossless features. A learned model's head trains on with its",
            "code, which changes its ego alone: its own gain kept, (with the codec - that model alone) / (reference",
            "lossless - reference alone), is the one to read; intervals paired over the test scenarios",
            '(`ros2_ws/benchmarks/bench_learned_codec.py`; BENCHMARKS.md, "V2X: a code learned for the wire").',
            "",
        ],
    )


def scan_section(results: Path) -> list[str]:
    """The senders' scans against the learned code and the transform codec on `test`
    (RESULTS/codec/scan-<range>-....json, `test` in the name)."""
    return _comparisons(
        results,
        "scan-*test.json",
        [
            "## The sender's scan instead of its features",
            "",
            "A LiDAR vehicle sends its voxelised scan (`send:=scan`) and each ego runs its own copy of the model on",
            "it, at the same byte budgets per neighbour-frame as the feature codecs; every row scored against",
            "`--reference` alone and with lossless features, intervals paired over the test scenarios",
            "(`ros2_ws/benchmarks/bench_learned_codec.py --scan`; BENCHMARKS.md, \"V2X: the sender's scan instead of",
            'its features").',
            "",
        ],
    )


def levers_section(results: Path) -> list[str]:
    """Single-agent checkpoints scored alone on `validate` (RESULTS/validate/<choice>/evaluation.json: one `evaluate`
    call with several --model and --collaborators 0), each row paired with the first and with the row above."""
    found = sorted((results / "validate").glob("*/evaluation.json"))
    if not found:
        return []
    out = [
        "## Ego stages alone on validate",
        "",
        "Single-agent checkpoints (a collaborative model's ego stage) scored with no collaborator on `validate`",
        "(never `test`), one `evaluate` call per table; each difference in mIoU 1..23 is paired over the same",
        "resampled scenarios.",
        "",
    ]
    for path in found:
        made = read_json(path, "evaluation")
        scored = [s for name, s in made.items() if name not in META]
        out += [
            f"### {path.parent.name}",
            "",
            f"Made by `{made.get('command', '')}`.",
            "",
            "| model | training steps | mIoU 1..23 | geometry IoU | vs the first row | vs the row above |",
            "|---|---|---:|---:|---:|---:|",
        ]
        boot = Bootstrap(list(scored[0]["per_scenario"]))  # one call: the same scenarios in every column

        def versus(run: dict, reference: dict) -> str:
            d = boot.difference(confusions_of(run), confusions_of(reference))["co3sop-code"]
            return f"{pct(d['delta'])} {span(d['ci95'])}"

        for i, s in enumerate(scored):
            out.append(
                f"| `{s.get('model', '?')}` | {recipe(s)} | {pct(point(s, 'co3sop-code'))} "
                f"{span(s['ci95']['co3sop-code'])} | "
                f"{pct(point(s, 'geometry'))} | "
                + (f"{versus(s, scored[0])} | {versus(s, scored[i - 1])} |" if i else "reference | - |")
            )
        out.append("")
    return out


def precision_section(results: Path) -> list[str]:
    """Reduced-precision inference against float32 on the same device and samples (`evaluate --ablation precision`,
    in results/precision/<model>-<precision>/)."""
    found = sorted((results / "precision").glob("*/*_precision.json"))
    if not found:
        return []
    lines = [
        "## Inference precision against float32 (mIoU over classes 1..23, %)",
        "",
        "The shipped weights on every test sample, float32 and the reduced precision on the same device; the",
        "difference is paired (the same resampled scenarios), the label agreement is over every voxel of every sample.",
        "",
        "| model | range | device | precision | float32 | this precision | difference [95 % interval] "
        "| labels equal to float32's |",
        "|---|---|---|---|---:|---:|---:|---:|",
    ]
    commands, int8 = [], False
    for path in found:
        report = read_json(path, "precision")
        precision = next(iter(report["differences"]))
        int8 = int8 or precision.startswith("int8")
        diff = report["differences"][precision]["co3sop-code"]
        name, rng = path.stem.removesuffix("_precision").rsplit("_", 1)
        device = report["device"] + (f" ({report['hardware']})" if "hardware" in report else "")
        shown = f"int8 (the rest {report['floats']})" if precision == "int8" and "floats" in report else precision
        lines.append(
            f"| {name} | {rng} | {device} | {shown} | {pct(point(report['float32'], 'co3sop-code'))} | "
            f"{pct(point(report[precision], 'co3sop-code'))} | {pct(diff['delta'])} {span(diff['ci95'])} | "
            f"{100 * report['label_agreement']:.2f} % of {report['voxels']:,} |"
        )
        commands.append(f"    {report['command']}")
    if int8:
        lines += [
            "",
            "int8: a calibrated LiDAR vehicle half's 3D layers after its first and the head's layers up to 1/2 in",
            "int8 (`calibrate`'s ranges, measured on `validate`; each half's int8 layers on weights fine-tuned for",
            "int8 on `train` where the checkpoint carries them, `calibrate --fine-tune`: the head's on the features",
            "the int8 vehicle halves make), the rest in bfloat16 where the CPU computes it: what `auto` takes for",
            "halves with fine-tuned int8 weights on a CPU with an int8 unit. int8 (vehicle halves bfloat16): the",
            "head's layers alone in int8, the features made in bfloat16, as an ego node on int8 fuses those of",
            "vehicle nodes on bfloat16; bfloat16 (vehicle halves int8): the vehicle halves alone in int8, as vehicle",
            "nodes on int8 beside an ego on bfloat16 (`evaluate --vehicle-precision`).",
        ]
    return [*lines, "", "Made by:", "", *commands, ""]


def distance_reading(bins: dict, rng: str) -> list[str]:
    """The distance table in one sentence: where the gain comes from, and how many samples have no one to help."""
    total = sum(b["samples"] for b in bins.values())
    parts = [
        f"{name}: {pct(b['difference']['co3sop-code']['delta'])} points on {pct(b['samples'] / total)} % of the samples"
        for name, b in bins.items()
    ]
    half = float(rng.rstrip("m")) / 2
    return [
        "Gain by the nearest collaborator's distance — " + "; ".join(parts) + ".",
        f"The {rng} grid spans {half:g} m each side of its agent, so a neighbour about {2 * half:g} m away "
        f"shares almost none",
        "of it: the share of samples in the far bins bounds the average gain this dataset allows.",
    ]


def training(seeds: dict[int, Path]) -> list[str]:
    """The train commands behind each seed's weights, as `evaluate` recorded them from the checkpoint: a run trained
    in pieces, or on another machine (its device, its own copy of the data), says so. A resume of a finished run
    (it trained no step) is left out; records older than `from_step` give the total steps only."""

    def steps(t: dict) -> str:
        return (
            f"{t['stage']} stage, started at step {t['from_step']} of {t['steps']}"
            if "from_step" in t
            else f"{t['stage']} stage, {t['steps']} steps"
        )

    lines, elsewhere = [], False
    for seed, folder in seeds.items():
        made = [t for t in _load(folder, "collaboration").get("trained", []) if t.get("from_step", -1) < t["steps"]]
        elsewhere |= any(" /tmp/" in t["command"] for t in made)
        lines += [f"- seed {seed}: " + "; then ".join(f"`{t['command']}` ({steps(t)})" for t in made)] if made else []
    if not lines:
        return []
    return [
        "#### Training commands",
        "",
        *(
            [
                "Folders under /tmp: the same dataset recipe generated, and the run started, on the machine "
                "with a GPU that trained it.",
                "",
            ]
            if elsewhere
            else []
        ),
        *lines,
        "",
    ]


def data_origin(results: Path) -> str:
    """Which data the evaluations under `results` ran on: each JSON's recorded `data` (its root, and whether this
    project's simulator wrote it), else the root its command names."""
    origins: dict[str, bool | None] = {}
    for path in sorted(results.rglob("*.json")):
        try:
            report = json.loads(path.read_text())
        except ValueError:
            continue  # read_json names a damaged file where a section needs it
        if not isinstance(report, dict):
            continue
        data, command = report.get("data"), report.get("command")
        if isinstance(data, dict) and isinstance(data.get("root"), str):
            origins[data["root"]] = bool(data.get("generated"))
        elif isinstance(command, str):
            for root in re.findall(r"--data (\S+)", command):
                origins.setdefault(root, None)
    said = {
        True: "written by this project's simulator, not Co3SOP's or OPV2V's recordings",
        False: "not written by this project's simulator",
        None: "origin not recorded in the evaluation",
    }
    return (
        "Data (the evaluations' `--data`): "
        + ("; ".join(f"`{root}` ({said[generated]})" for root, generated in sorted(origins.items())) or "none recorded")
        + "."
    )


def render(results: Path, command: str, target: Goals | None = None) -> str:
    runs = collect(results)
    out = [
        "# Benchmark results (test split)",
        "",
        f"Generated by `{command}` from the JSON of `evaluate` in `{results}`; do not edit by hand.",
        data_origin(results),
        "The protocol (dataset recipe `config/benchmark.yaml`, training on `train`, every choice on `validate`,",
        "this page on `test` only) and the commands that made every run: `ros2_ws/run_protocol.sh`.",
        "Intervals: 95 % percentile bootstrap over test scenarios (2000 resamples); gains are paired",
        "(both sides on the same resampled scenarios). Mean ± standard deviation over training seeds.",
        "",
        "## Collaboration gain (mIoU over classes 1..23, %)",
        "",
        "`off` is the fusion model with no collaborator: the same weights and training, the reference of the gain.",
        "`ego stage alone` is the single-agent model the fusion stage started from; its head had fewer training",
        "steps (the fusion stage trains it further), so the gain over it overstates what collaboration adds.",
        *(
            [
                "An early-fusion model (the collaborators' LiDAR scans merged into the ego's before one network) has",
                "one stage; its `off` is the same network given the ego's scan only.",
            ]
            if any(model_preset(n).early_fusion for n, _, _ in runs)
            else []
        ),
        "",
        *headline(runs),
        "",
        *(
            ["Against the protocol's goals (computed from the table above):", "", *goals(runs, results, target), ""]
            if target is not None
            else []
        ),
        *table2_section(results, runs),
        *across_ranges(
            runs,
            "collaborators",
            "Number of collaborators, nearest first",
            "The paper (its camera Co3SOP-Base, a figure without printed values): the gain comes mainly from the 1-2"
            " nearest collaborators; at 25.6 m only the closest helps, at 51.2 and 76.8 m more of them add to it.",
        ),
        *across_ranges(
            runs,
            "pose_noise",
            "Pose noise (sigma 0.02 m, neighbours only)",
            "The paper's column: its camera Co3SOP-Base on its CARLA data (compare the trend, not the level).",
            PAPER_POSE_NOISE,
        ),
        *single_agent_section(results),
        *precision_section(results),
        *validate_section(results),
        *levers_section(results),
        *wire_code_section(results),
        *scan_section(results),
        *observed_section(results),
    ]
    for (preset, rng, steps), seeds in runs.items():
        first = seeds[min(seeds)]
        out += [f"## {preset}, {rng}, {steps}", "", *training(seeds)]
        out += compact(_load(first, "inputs"), f"Input controls (seed {min(seeds)})")
        for seed, folder in seeds.items():
            out += compact(_load(folder, "collaboration"), f"Collaboration off / on (seed {seed})")
        out += compact(_load(first, "collaborators"), f"Number of collaborators, nearest first (seed {min(seeds)})")
        out += compact(_load(first, "pose_noise"), f"Pose noise (seed {min(seeds)})")
        distance = _load(first, "distance")
        if distance:
            out += [
                f"#### Collaboration gain by the nearest collaborator's distance (seed {min(seeds)})",
                "",
                distance["title"],
                "",
                f"Made by `{distance['command']}`. Each row: the samples whose nearest collaborator (in the",
                f"{COMM_RANGE:g} m communication range) is that far, 95 % intervals over the test scenarios "
                f"that have such samples.",
                "",
                *distance_table(distance["bins"]),
                "",
                *distance_reading(distance["bins"], rng),
                "",
            ]
        report = _load(first, "collaboration")
        runs_pc = {k: v for k, v in report.items() if isinstance(v, dict) and "ci95" in v}
        out += [f"#### Per-class IoU (%), collaboration off / on (seed {min(seeds)})", "", markdown_table(runs_pc), ""]
    return "\n".join(out)


def write_report(results: Path, out: Path, goals_from: Path | None = None) -> int:
    """The page for the evaluation folders under `results`, written atomically to `out`; with `goals_from` (a
    protocol recipe), each model set against the recipe's goals."""
    if not results.is_dir():
        raise Co3sopError(f"{results}: not a folder")
    target = read_goals(goals_from) if goals_from is not None else None
    command = f"report {results} --out {out}" + (f" --goals {goals_from}" if goals_from is not None else "")
    text = render(results, command, target)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(text + "\n")
    tmp.replace(out)  # atomic: a failed run leaves the previous page
    print(f"report: {out}")
    return 0
