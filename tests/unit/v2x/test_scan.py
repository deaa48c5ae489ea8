"""Unit tests of the scan codec (ROS-free): a sender's voxelised scan round-trips bit for bit, a budget keeps the
voxels nearest the sensor, every field a hostile sender could set is refused by name, and an ego that encodes a
received scan has exactly the sender's features."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import zstandard

from co3sop_nodes.common.errors import (
    CodecError,
    CorruptPayloadError,
    PayloadTooLargeError,
    SizeMismatchError,
    UnknownCodecError,
)
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.inference.outputs import scan_output, through_scan
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.v2x.scan import ScanCodecConfig, decode_scan, encode_scan

GRID = GridSpec((-6.4, -6.4, -2.0), 0.2, (64, 64, 12))


def scan(seed: int = 0, share: float = 0.03) -> np.ndarray:
    """(X, Y, Z) uint8: a sparse occupancy grid, with a ground layer as a LiDAR sees."""
    rng = np.random.default_rng(seed)
    occ = (rng.uniform(size=GRID.dims) < share).astype(np.uint8)
    occ[:, :, 2] |= rng.uniform(size=GRID.dims[:2]) < 0.5
    return occ


@pytest.mark.parametrize("codec", ["zstd", "none"])
def test_a_scan_round_trips_bit_for_bit(codec):
    occ = scan()
    enc = encode_scan(occ, GRID, ScanCodecConfig(codec=codec))
    assert enc.num_voxels == int(occ.sum()) and enc.occupancy_raw_size == GRID.num_voxels // 8
    np.testing.assert_array_equal(decode_scan(enc), occ.astype(bool))
    if codec == "zstd":
        assert enc.budget_bytes < enc.occupancy_raw_size / 2


def test_a_budget_keeps_the_voxels_nearest_the_sensor():
    occ = scan(1)
    whole = encode_scan(occ, GRID, ScanCodecConfig())
    budget = whole.budget_bytes // 2
    enc = encode_scan(occ, GRID, ScanCodecConfig(max_bytes=budget))
    assert enc.budget_bytes <= budget
    kept = decode_scan(enc)
    assert 0 < kept.sum() < occ.sum() and not (kept & ~occ.astype(bool)).any()
    centres = np.stack(np.indices(GRID.dims), -1) * GRID.voxel_size + np.add(GRID.origin, GRID.voxel_size / 2)
    distance = np.linalg.norm(centres, axis=-1)
    assert distance[kept].max() <= distance[occ.astype(bool) & ~kept].min() + 1e-9
    assert encode_scan(occ, GRID, ScanCodecConfig(max_bytes=whole.budget_bytes)).num_voxels == occ.sum()


def test_a_budget_below_an_empty_scan_is_refused():
    with pytest.raises(CodecError, match="max_bytes 5: even an empty scan"):
        encode_scan(scan(), GRID, ScanCodecConfig(max_bytes=5))


def test_a_scan_of_another_shape_is_refused():
    with pytest.raises(SizeMismatchError, match="occupancy: shape"):
        encode_scan(scan()[:-1], GRID, ScanCodecConfig())


@pytest.mark.parametrize(
    ("fields", "error", "match"),
    [
        ({"codec": "lz4"}, UnknownCodecError, "unknown codec 'lz4'"),
        ({"occupancy_raw_size": 10**12}, PayloadTooLargeError, "occupancy: declares"),
        ({"occupancy_raw_size": 7}, SizeMismatchError, "occupancy: declares 7"),
        ({"occupancy": b"\x28\xb5\x2f\xfd" + bytes(20)}, CorruptPayloadError, "occupancy"),
        ({"num_voxels": 3}, SizeMismatchError, "num_voxels: declares 3"),
        ({"occupancy": b"", "codec": "none"}, SizeMismatchError, "occupancy: carries 0 bytes"),
    ],
)
def test_a_hostile_scan_is_refused_by_field(fields, error, match):
    enc = encode_scan(scan(), GRID, ScanCodecConfig())
    with pytest.raises(error, match=match):
        decode_scan(dataclasses.replace(enc, **fields), max_raw_bytes=1 << 20)


def test_a_frame_declaring_another_size_is_refused_before_decompressing():
    bomb = zstandard.ZstdCompressor(write_checksum=True).compress(bytes(1 << 20))
    enc = dataclasses.replace(encode_scan(scan(), GRID, ScanCodecConfig()), occupancy=bomb)
    with pytest.raises(CorruptPayloadError, match="zstd frame declares 1048576 bytes"):
        decode_scan(enc)


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"codec": "gzip"}, "unknown codec"),
        ({"level": -1}, "level must be"),
        ({"max_bytes": 1.5}, "max_bytes must be"),
        ({"max_bytes": True}, "max_bytes must be"),
        ({"burst_bytes": 10}, "burst_bytes 10 needs a max_bytes"),
        ({"max_bytes": 100, "burst_bytes": 50}, "burst_bytes 50 needs"),
    ],
)
def test_bad_settings_are_refused_by_name(fields, match):
    with pytest.raises(CodecError, match=match):
        ScanCodecConfig(**fields)


def test_names():
    assert ScanCodecConfig().name == "scan-zstd"
    assert ScanCodecConfig(max_bytes=8192, burst_bytes=16384).name == "scan8KB-burst16KB-zstd"


def test_an_ego_encoding_a_received_scan_has_the_senders_features_exactly():
    torch.manual_seed(0)
    model = build_model(preset("tiny-lidar")).eval()
    occ = (np.random.default_rng(2).uniform(size=model.cfg.grid.dims) < 0.02).astype(np.uint8)
    with torch.no_grad():
        sender = model.vehicle(occupancy=torch.from_numpy(occ)[None, None])
    received, size = through_scan(model, occ[None], ScanCodecConfig())
    assert size > 0
    torch.testing.assert_close(received.features, sender.features, atol=0, rtol=0)
    torch.testing.assert_close(received.confidence, sender.confidence, atol=0, rtol=0)


def test_a_camera_model_or_another_grid_encodes_no_scan():
    camera = build_model(preset("tiny")).eval()
    enc = encode_scan(np.zeros(camera.cfg.grid.dims, bool), camera.cfg.grid, ScanCodecConfig())
    with pytest.raises(CodecError, match="a camera model encodes no LiDAR scan"):
        scan_output(enc, camera)
    lidar = build_model(preset("tiny-lidar")).eval()
    with pytest.raises(CodecError, match="grid 64x64x12 @ 0.2 m does not match the model's 256x256x24 @ 0.2 m"):
        scan_output(encode_scan(scan(), GRID, ScanCodecConfig()), lidar)
    coarser = GridSpec(lidar.cfg.grid.origin, 0.4, lidar.cfg.grid.dims)  # as many voxels, of another size
    with pytest.raises(CodecError, match="grid 256x256x24 @ 0.4 m does not match"):
        scan_output(encode_scan(np.zeros(coarser.dims, bool), coarser, ScanCodecConfig()), lidar)
