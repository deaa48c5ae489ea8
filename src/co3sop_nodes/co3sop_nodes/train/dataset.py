"""Samples for training and evaluation: every CAV of every frame is the ego in turn (as Co3SOP).

A sample is the ego's inputs and labels plus its collaborators (other CAVs of the frame within the
communication range, nearest first), each with its inputs and the transform neighbour_from_ego between the
two LiDAR frames. Only an index stays in memory (per frame: its CAVs and their LiDAR poses, read from the
OPV2V yaml files once); an agent's inputs and labels are read from disk when a sample needs them, so memory
does not grow with the dataset. With a cache folder, an agent's preprocessed inputs and labels (the LiDAR
occupancy or the resized images) are written there the first time and read back instead of decoding PNG,
PCD and label files again; an entry's name holds everything it depends on (the model's sensor settings and
range, and the size and time of every source file), so a changed preset, range or file never reads a stale
entry.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import OrderedDict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.data import opv2v
from co3sop_nodes.inference.inputs import camera_inputs, lidar_occupancy, merged_occupancy
from co3sop_nodes.model.config import ModelConfig
from co3sop_nodes.v2x.neighbours import nearest_collaborators

CACHE_VERSION = 1  # raised whenever what an entry holds changes


@dataclass
class AgentRecord:
    cav_id: int
    world_from_lidar: np.ndarray  # (4, 4)
    inputs: dict  # numpy VehicleHalf inputs (images + lidar2img, or occupancy)
    labels: np.ndarray | None  # (X, Y, Z) uint8 at the model's range

    def pin_memory(self) -> AgentRecord:
        """A copy whose inputs and labels lie in page-locked memory (see Sample.pin_memory)."""
        labels = None if self.labels is None else _pinned(self.labels)
        return replace(self, inputs={k: _pinned(v) for k, v in self.inputs.items()}, labels=labels)


@dataclass
class Sample:
    key: tuple[str, str, int, int]  # split, scenario, timestamp, ego cav
    ego: AgentRecord
    others: list[AgentRecord]  # nearest first
    neighbour_from_ego: np.ndarray  # (A, 4, 4)

    def pin_memory(self) -> Sample:
        """The DataLoader's hook for a custom batch type (`pin_memory=True`, on CUDA): a copy whose arrays that a
        step sends to the GPU lie in page-locked memory, which the GPU reads directly; the loader's pinning thread
        makes it while the step before trains."""
        return replace(self, ego=self.ego.pin_memory(), others=[a.pin_memory() for a in self.others])


def _pinned(array: np.ndarray) -> np.ndarray:
    """`array`'s values in page-locked memory, as a NumPy view that keeps its tensor alive."""
    dtype = torch.from_numpy(np.empty(0, array.dtype)).dtype
    out = torch.empty(array.shape, dtype=dtype, pin_memory=True).numpy()
    out[...] = array
    return out


@dataclass(frozen=True)
class FrameIndex:
    """What the index keeps of one frame: where it is, its CAVs (folder names, OpenCOOD order), their poses."""

    key: tuple[str, str, int]  # split, scenario, timestamp
    cavs: tuple[str, ...]
    poses: np.ndarray  # (A, 4, 4) world_from_lidar

    @property
    def cav_ids(self) -> list[int]:
        return [int(c) for c in self.cavs]


def early_fused(sample: Sample, grid: GridSpec, scan=lambda record: record.inputs["occupancy"]) -> Sample:
    """The sample as an early-fusion model sees it: the ego's scan merged with its collaborators' (`scan`: an
    agent's (1, X, Y, Z) occupancy, its own by default, or an input control's), and no collaborator left to fuse."""
    merged = merged_occupancy(scan(sample.ego), [scan(a) for a in sample.others], sample.neighbour_from_ego, grid)
    return replace(
        sample, ego=replace(sample.ego, inputs={"occupancy": merged}), others=[], neighbour_from_ego=np.zeros((0, 4, 4))
    )


class OccupancyDataset:
    """The samples of `splits` under an OPV2V / Co3SOP root, read on demand (see the module docstring).

    `cache`: a folder for preprocessed agents (None: none); `keep`: agents kept in memory, most recent first
    (a sample and the next ones of its frame read the same agents)."""

    def __init__(
        self,
        root: Path,
        splits: list[str],
        cfg: ModelConfig,
        max_scenarios: int | None = None,
        cache: Path | None = None,
        keep: int = 16,
    ):
        self.root, self.cfg, self.keep = Path(root), cfg, keep
        self.cache = Path(cache) / self._settings_key() if cache is not None else None
        self._recent: OrderedDict[tuple[int, int], AgentRecord] = OrderedDict()
        self.frames: list[FrameIndex] = []
        scenarios = [(s, n) for s, n in opv2v.find_scenarios(self.root) if s in splits][:max_scenarios]
        if not scenarios:
            raise DatasetError(f"{self.root}: no scenarios in split(s) {', '.join(splits)}")
        for split, name in scenarios:
            cavs, timestamps = opv2v.scenario_timestamps(self.root / split / name)
            for ts in timestamps:
                poses = np.stack([opv2v.read_lidar_pose(self.root, split, name, cav, ts) for cav in cavs])
                self.frames.append(FrameIndex((split, name, ts), tuple(cavs), poses))
        self.scenarios = list(dict.fromkeys(frame.key[:2] for frame in self.frames))  # (split, name), in order
        self.index = [(f, j) for f, frame in enumerate(self.frames) for j in range(len(frame.cavs))]

    def __len__(self) -> int:
        return len(self.index)

    def __getstate__(self) -> dict:  # a DataLoader worker starts with an empty memory of recent agents
        return {**self.__dict__, "_recent": OrderedDict()}

    def _settings_key(self) -> str:
        """What a cache entry depends on besides its files: the model's sensor settings and range."""
        cfg = self.cfg
        grid = cfg.grid
        settings = {
            "version": CACHE_VERSION,
            "modality": cfg.modality,
            "range": cfg.range,
            "image_size": list(cfg.image_size) if cfg.modality == "camera" else None,
            "grid": [list(grid.origin), grid.voxel_size, list(grid.dims)],
        }
        return hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]

    def agent(self, f: int, j: int) -> AgentRecord:
        """Agent j of frame f, its inputs and labels read from disk (or the cache)."""
        if (f, j) in self._recent:
            self._recent.move_to_end((f, j))
            return self._recent[(f, j)]
        record = self._read(f, j)
        self._recent[(f, j)] = record
        while len(self._recent) > self.keep:
            self._recent.popitem(last=False)
        return record

    def _read(self, f: int, j: int) -> AgentRecord:
        frame = self.frames[f]
        (split, name, ts), cav = frame.key, frame.cavs[j]
        lidar = self.cfg.modality == "lidar"
        entry = None
        if self.cache is not None:
            files = opv2v.cav_frame_files(self.root, split, name, cav, ts, (self.cfg.range,), points=lidar)
            try:
                stamp = hashlib.sha1(repr([(p.name, *_size_and_time(p)) for p in files]).encode())
            except FileNotFoundError as exc:
                raise DatasetError(f"{exc.filename}: missing") from None
            entry = self.cache / split / name / f"{cav}_{ts:06d}_{stamp.hexdigest()[:12]}.npz"
            if entry.is_file():
                with np.load(entry) as data:
                    arrays = dict(data)
                labels = arrays.pop("labels", None)
                return AgentRecord(int(cav), frame.poses[j], arrays, labels)
        cav_frame = opv2v.read_cav_frame(self.root, split, name, cav, ts, (self.cfg.range,), points=lidar)
        if lidar:
            inputs = {"occupancy": lidar_occupancy(cav_frame.points, self.cfg.grid)}
        else:
            images, lidar2img = camera_inputs(cav_frame.cameras, cav_frame.world_from_lidar, self.cfg.image_size)
            inputs = {"images": images, "lidar2img": lidar2img}
        labels = cav_frame.labels.get(self.cfg.range)
        if entry is not None:
            _write_entry(entry, {**inputs, **({"labels": labels} if labels is not None else {})})
        return AgentRecord(int(cav), frame.poses[j], inputs, labels)

    def sample(self, i: int, max_collaborators: int | None = None) -> Sample:
        f, j = self.index[i]
        frame = self.frames[f]
        k = self.cfg.max_collaborators if max_collaborators is None else max_collaborators
        ids = frame.cav_ids
        poses = {ids[m]: frame.poses[m] for m in range(len(ids)) if m != j}
        chosen = nearest_collaborators(frame.poses[j], poses, k=k)
        ego = self.agent(f, j)
        others = [self.agent(f, ids.index(c)) for c in chosen]
        rel = (
            np.stack([np.linalg.inv(a.world_from_lidar) @ ego.world_from_lidar for a in others])
            if others
            else np.zeros((0, 4, 4))
        )
        return Sample((*frame.key, ego.cav_id), ego, others, rel)


def _size_and_time(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_size, st.st_mtime_ns


def _write_entry(path: Path, arrays: dict) -> None:
    """Atomically: DataLoader workers and concurrent runs may write the same entry."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)
