"""What a bag, a folder of bags, a recording or an OPV2V/Co3SOP dataset folder holds: scenarios, CAVs, frames,
topics, and per-class voxel counts of the ground truth per benchmark range."""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from co3sop_nodes.common import topics
from co3sop_nodes.common.classes import CLASS_NAMES, NUM_CLASSES
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.progress import progress
from co3sop_nodes.data import opv2v
from co3sop_nodes.data.bags import occupancy_labels, open_reader, open_recording
from co3sop_nodes.messages import OCCUPANCY


def class_table(counts: dict[str, np.ndarray]) -> str:
    """Markdown table: one row per class present, one column per range (voxels and share)."""
    ranges = sorted(counts)
    lines = ["| class | " + " | ".join(ranges) + " |", "|---|" + "---:|" * len(ranges)]
    for label in range(NUM_CLASSES + 1):
        if not any(counts[r][label] for r in ranges):
            continue
        name = CLASS_NAMES[label] if label < NUM_CLASSES else "ignore (255)"
        cells = [f"{int(counts[r][label])} ({counts[r][label] / max(counts[r].sum(), 1):.2%})" for r in ranges]
        lines.append(f"| {label if label < NUM_CLASSES else 255} {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _count(labels: np.ndarray) -> np.ndarray:
    """(NUM_CLASSES + 1,) voxel counts; the last entry counts ignored (255) voxels."""
    c = np.bincount(labels.reshape(-1), minlength=256)
    return np.append(c[:NUM_CLASSES], c[255])


def bag_info(path: Path, counts: bool) -> str:
    """A bag folder, or a recording (one MCAP file): its topics, CAVs, frames and ground-truth classes."""
    rows, cavs, stamps = [], set(), set()
    class_counts: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(NUM_CLASSES + 1, np.int64))
    recording = path.is_file()
    with open_recording(path) if recording else open_reader(path) as reader:
        for conn in sorted(reader.connections, key=lambda c: c.topic):
            rows.append(f"| {conn.topic} | {conn.msgtype} | {conn.msgcount} |")
            if (cav := topics.split_cav_topic(conn.topic)) is not None:
                cavs.add(cav[0])
        messages = reader.message_count
        duration = (reader.end_time - reader.start_time) / 1e9 if messages else 0.0
        for _, stamp, _ in reader.messages(
            connections=[c for c in reader.connections if c.topic.endswith("/lidar/pose")]
        ):
            stamps.add(stamp)
        if counts:
            # ground-truth grids only: a recording also holds their point clouds (/ego/ground_truth/points)
            gt = [c for c in reader.connections if "/ground_truth/" in c.topic and c.msgtype == OCCUPANCY]
            for conn, stamp, raw in reader.messages(connections=gt):
                msg = reader.deserialize(raw, conn, stamp)
                with reader.about(conn, stamp):
                    labels, grid = occupancy_labels(msg)
                class_counts[f"{grid.extent[0]:.1f}m"] += _count(labels)
    frames = f"; {len(stamps)} frames" if stamps or not recording else ""  # a recording has no sensor poses
    out = [
        f"# {path}",
        f"{'MCAP file' if recording else 'bag'}: {messages} messages over {duration:.1f} s; CAVs "
        f"{sorted(cavs)}{frames}",
        "",
        "| topic | type | messages |",
        "|---|---|---:|",
        *rows,
    ]
    if class_counts:
        out += ["", "Ground-truth voxels per class:", "", class_table(class_counts)]
    return "\n".join(out)


def folder_info(root: Path, counts: bool) -> str:
    scenarios = opv2v.find_scenarios(root)
    out = [
        f"# {root}",
        f"{len(scenarios)} scenario(s): " + ", ".join(f"{s} {n}" for s, n in Counter(s for s, _ in scenarios).items()),
        "",
        "| split | scenario | CAVs (ego first) | frames | label ranges |",
        "|---|---|---|---:|---|",
    ]
    class_counts: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(NUM_CLASSES + 1, np.int64))
    files = []
    for split, name in scenarios:
        cavs, timestamps = opv2v.scenario_timestamps(root / split / name)
        ranges = [r for r, folder in opv2v.LABEL_FOLDERS.items() if (root / folder / split / name).is_dir()]
        out.append(f"| {split} | {name} | {' '.join(cavs)} | {len(timestamps)} | {' '.join(ranges) or '-'} |")
        files += [
            (r, opv2v.label_path(root, r, split, name, int(c), t)) for r in ranges for c in cavs for t in timestamps
        ]
    if counts and files:
        bar = progress(len(files), "label files", "file")
        for range_name, path in files:
            if path.exists():
                class_counts[range_name] += _count(opv2v.read_labels(path, range_name))
            bar.update(1)
        bar.close()
        out += ["", "Ground-truth voxels per class:", "", class_table(class_counts)]
    return "\n".join(out)


def describe(path: Path, counts: bool = True) -> str:
    """The summary of whatever `path` is (see the module docstring); counts: also the per-class voxel counts."""
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    if path.is_file() or (path / "metadata.yaml").is_file():
        return bag_info(path, counts)
    if bags := sorted(p.parent for p in path.glob("**/metadata.yaml")):
        return "\n\n".join(bag_info(bag, counts) for bag in bags)
    return folder_info(path, counts)
