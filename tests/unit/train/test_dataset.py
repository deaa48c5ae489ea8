"""Samples streamed from disk: an index in memory, agents read on demand, an on-disk cache that is never stale,
and each step's samples read ahead by DataLoader workers in the run's order."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.data import opv2v
from co3sop_nodes.inference.inputs import camera_inputs, lidar_occupancy
from co3sop_nodes.model.config import preset
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.train.loader import StepSamples, step_loader
from co3sop_nodes.train.trainer import sample_order, training_sample

FIXTURE = Path(__file__).resolve().parents[2] / "fixtures" / "opv2v"
SCENARIO = "2021_08_24_21_29_28"
CAMERA = preset("tiny", image_size=(64, 48))
LIDAR = preset("tiny-lidar")


@pytest.fixture
def root(tmp_path) -> Path:
    shutil.copytree(FIXTURE, tmp_path / "opv2v")
    return tmp_path / "opv2v"


def counting_reads(monkeypatch) -> list:
    reads = []
    original = opv2v.read_cav_frame

    def read(*args, **kwargs):
        reads.append(args[3:5])  # (cav, timestamp)
        return original(*args, **kwargs)

    monkeypatch.setattr(opv2v, "read_cav_frame", read)
    return reads


def test_samples_are_read_on_demand_and_only_a_few_agents_stay_in_memory(root, monkeypatch):
    reads = counting_reads(monkeypatch)
    dataset = OccupancyDataset(root, ["test"], CAMERA, keep=2)
    assert (len(dataset), len(dataset.frames), reads) == (4, 2, [])  # the index reads no sensor file
    for i in range(len(dataset)):
        sample = dataset.sample(i)
        assert len(dataset._recent) <= 2
        frame = opv2v.read_cav_frame(root, "test", SCENARIO, str(sample.ego.cav_id), sample.key[2], ("51.2m",))
        images, lidar2img = camera_inputs(frame.cameras, frame.world_from_lidar, CAMERA.image_size)
        assert np.array_equal(sample.ego.inputs["images"], images)
        assert np.array_equal(sample.ego.inputs["lidar2img"], lidar2img)
        assert np.array_equal(sample.ego.labels, frame.labels["51.2m"])
        assert np.allclose(sample.ego.world_from_lidar, frame.world_from_lidar)
        assert [a.cav_id for a in sample.others] == [c for c in (4805, 4814) if c != sample.ego.cav_id]


def test_the_cache_holds_what_decoding_gives_and_is_read_instead(root, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    first = OccupancyDataset(root, ["test"], LIDAR, cache=cache)
    decoded = [first.sample(i) for i in range(len(first))]
    frame = opv2v.read_cav_frame(root, "test", SCENARIO, "4805", 69)
    assert np.array_equal(decoded[0].ego.inputs["occupancy"], lidar_occupancy(frame.points, LIDAR.grid))
    reads = counting_reads(monkeypatch)
    again = OccupancyDataset(root, ["test"], LIDAR, cache=cache)
    for i, want in enumerate(decoded):
        got = again.sample(i)
        assert np.array_equal(got.ego.inputs["occupancy"], want.ego.inputs["occupancy"])
        assert np.array_equal(got.ego.labels, want.ego.labels) and got.ego.labels.dtype == np.uint8
    assert reads == []  # every agent from the cache


def test_a_changed_preset_range_or_file_never_reads_a_stale_entry(root, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    OccupancyDataset(root, ["test"], CAMERA, cache=cache).sample(0)
    reads = counting_reads(monkeypatch)
    OccupancyDataset(root, ["test"], preset("tiny", image_size=(32, 24)), cache=cache).sample(0)
    OccupancyDataset(root, ["test"], preset("tiny", image_size=(64, 48), range="25.6m"), cache=cache).sample(0)
    assert len(reads) == 4 and len(list(cache.iterdir())) == 3  # each sample's two agents; one folder per setting
    png = root / "test" / SCENARIO / "4805" / "000069_camera0.png"
    os.utime(png, ns=(png.stat().st_atime_ns, png.stat().st_mtime_ns + 10**9))  # the image was replaced
    OccupancyDataset(root, ["test"], CAMERA, cache=cache).sample(0)
    assert reads[4:] == [("4805", 69)]  # only the agent whose file changed is read again


def test_each_step_gets_its_samples_in_the_run_order_whatever_the_workers(root):
    dataset = OccupancyDataset(root, ["test"], LIDAR)
    order = sample_order(len(dataset), 3, 6 * 2)
    prepare = training_sample(LIDAR, "fusion")
    for rank in (0, 1):  # two processes of a torchrun world, one sample each per step of global batch 2
        steps = StepSamples(dataset, order, 1, 6, 2, rank, 1, prepare)
        want = [[dataset.sample(int(order[p])).key for p in steps.places(step)] for step in range(1, 6)]
        for workers in (0, 2):
            got = [[s.key for s in samples] for samples in step_loader(steps, workers)]
            assert got == want, workers


def test_a_sample_that_cannot_be_read_comes_back_as_its_error(root):
    (root / "test" / SCENARIO / "4814" / "000071_camera1.png").write_bytes(b"not a png")
    dataset = OccupancyDataset(root, ["test"], CAMERA)
    steps = StepSamples(dataset, np.arange(4), 0, 4, 1, 0, 1, training_sample(CAMERA, "fusion"))
    items = list(step_loader(steps, 2))
    assert isinstance(items[0], list)
    assert isinstance(items[3], DatasetError) and "000071_camera1.png" in str(items[3])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (CI has none)")
def test_samples_for_a_cuda_step_come_in_page_locked_memory_with_the_same_values(root):
    dataset = OccupancyDataset(root, ["test"], CAMERA)
    steps = StepSamples(dataset, np.arange(2), 0, 2, 1, 0, 1, training_sample(CAMERA, "joint"))
    for workers in (0, 2):
        for k, samples in enumerate(step_loader(steps, workers, torch.device("cuda"))):
            for got, want in zip(samples, steps[k]):
                for g, w in zip([got.ego, *got.others], [want.ego, *want.others]):
                    arrays = [(g.inputs[n], w.inputs[n]) for n in w.inputs]
                    arrays += [(g.labels, w.labels)] if w.labels is not None else []
                    for pinned, plain in arrays:
                        assert torch.from_numpy(pinned).is_pinned() and pinned.dtype == plain.dtype
                        np.testing.assert_array_equal(pinned, plain)
