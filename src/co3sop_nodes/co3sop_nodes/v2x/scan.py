"""A sender's voxelised LiDAR scan as a V2X message (ROS-free): the occupancy grid a LiDAR model's vehicle half
takes, sent instead of the features it makes, for the ego's copy of the model to encode.

A LiDAR vehicle half is a function of this grid alone, so an ego that encodes a received scan has exactly the
features the sender would have sent, for the cost of running the vehicle half once per neighbour. The grid is
sparse and layered (the ground, then what stands on it), so its bits go slice by slice from the lowest, each
slice's in x-major order ((z, x, y) C order, numpy packbits' little bit order), which compresses about a third
smaller than the grid's own flat (x, y, z) order. Under a byte budget the scan keeps the occupied voxels nearest
the sensor (the grid frame's origin), as many as fit.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np

from co3sop_nodes.common.errors import CodecError, SizeMismatchError
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.v2x.codec import (
    CODECS,
    DEFAULT_MAX_RAW_BYTES,
    SIZE_NOISE_SHIFT,
    check_choice,
    compress_payload,
    decompress_payload,
    payload_codec,
    resolved_level,
)


@dataclass(frozen=True)
class ScanCodecConfig:
    """How a vehicle sends its scan."""

    codec: str = "zstd"  # "zstd" | "shuffle-zstd" (the same on bits) | "none"
    level: int = 3  # zstd level (0: the codec's own, ZSTD_LEVELS)
    max_bytes: int = 0  # > 0: the nearest occupied voxels that fit this many bytes (0: the whole scan)
    # > max_bytes: max_bytes is the average per message to one receiver and this the most one message may take
    # (v2x/sender_budget.py)
    burst_bytes: int = 0

    def __post_init__(self) -> None:
        check_choice("codec", self.codec, CODECS)
        for name in ("level", "max_bytes", "burst_bytes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
                raise CodecError(f"{name} must be a whole number >= 0, got {value!r}")
        if self.burst_bytes and (not self.max_bytes or self.burst_bytes < self.max_bytes):
            raise CodecError(
                f"burst_bytes {self.burst_bytes} needs a max_bytes budget of at most it (max_bytes {self.max_bytes})"
            )

    @property
    def name(self) -> str:
        """Short label, e.g. 'scan7KB-zstd'."""
        budget = f"{self.max_bytes // 1024}KB" if self.max_bytes else ""
        burst = f"-burst{self.burst_bytes // 1024}KB" if self.burst_bytes else ""
        return f"scan{budget}{burst}-{self.codec}"


@dataclass(frozen=True)
class EncodedScan:
    """A scan as carried by co3sop_msgs/VoxelScan (minus header and pose)."""

    grid: GridSpec
    codec: str
    num_voxels: int  # occupied voxels carried
    occupancy: bytes  # codec(bits of the grid in (z, x, y) order)
    occupancy_raw_size: int  # ceil(nx * ny * nz / 8)

    @property
    def payload_bytes(self) -> int:
        """Compressed bytes of the payload."""
        return len(self.occupancy)

    @property
    def budget_bytes(self) -> int:
        """What a byte budget counts: the payload."""
        return self.payload_bytes


def _encode(occupied: np.ndarray, grid: GridSpec, cfg: ScanCodecConfig) -> EncodedScan:
    """occupied (nx, ny, nz) bool -> its message."""
    raw = np.packbits(occupied.transpose(2, 0, 1).reshape(-1), bitorder="little").tobytes()
    codec = payload_codec(cfg.codec, 1)  # bytes of bits
    return EncodedScan(
        grid, codec, int(occupied.sum()), compress_payload(raw, codec, resolved_level(codec, cfg.level)), len(raw)
    )


def encode_scan(occupancy: np.ndarray, grid: GridSpec, cfg: ScanCodecConfig) -> EncodedScan:
    """An occupancy grid (nx, ny, nz) (nonzero: occupied) in the sender's LiDAR frame -> its message: all of it, or
    under cfg.max_bytes the most occupied voxels nearest the sensor whose message fits (within 1 / 256 of the
    largest count: compression noise makes a finer search pointless)."""
    occupancy = np.asarray(occupancy)
    if occupancy.shape != grid.dims:
        raise SizeMismatchError(f"occupancy: shape {occupancy.shape} does not match the grid {grid.dims}")
    occupied = occupancy != 0
    whole = _encode(occupied, grid, cfg)
    if not cfg.max_bytes or whole.budget_bytes <= cfg.max_bytes:
        return whole
    index = np.flatnonzero(occupied)
    centres = np.stack(np.unravel_index(index, grid.dims), 1) * grid.voxel_size + np.add(
        grid.origin, grid.voxel_size / 2
    )
    order = index[np.argsort(np.linalg.norm(centres, axis=1), kind="stable")]  # nearest the sensor first

    def nearest(k: int) -> EncodedScan:
        kept = np.zeros(grid.num_voxels, bool)
        kept[order[:k]] = True
        return _encode(kept.reshape(grid.dims), grid, cfg)

    best = nearest(0)
    if best.budget_bytes > cfg.max_bytes:
        raise CodecError(f"max_bytes {cfg.max_bytes}: even an empty scan takes {best.budget_bytes} bytes")
    lo, over = 0, len(order)  # lo fits, over does not
    while over - lo > max(1, lo >> SIZE_NOISE_SHIFT):
        k = (lo + over) // 2
        enc = nearest(k)
        if enc.budget_bytes <= cfg.max_bytes:
            lo, best = k, enc
        else:
            over = k
    return best


def decode_scan(enc: EncodedScan, max_raw_bytes: int = DEFAULT_MAX_RAW_BYTES) -> np.ndarray:
    """Inverse of encode_scan: the occupancy grid (nx, ny, nz) bool; raises a CodecError subclass naming the bad
    field."""
    grid = enc.grid
    raw = decompress_payload(
        enc.occupancy, enc.codec, enc.occupancy_raw_size, -(-grid.num_voxels // 8), "occupancy", max_raw_bytes
    )
    bits = np.unpackbits(np.frombuffer(raw, np.uint8), count=grid.num_voxels, bitorder="little").astype(bool)
    if int(bits.sum()) != enc.num_voxels:
        raise SizeMismatchError(f"num_voxels: declares {enc.num_voxels} but occupancy sets {int(bits.sum())}")
    nx, ny, nz = grid.dims
    return np.ascontiguousarray(bits.reshape(nz, nx, ny).transpose(1, 2, 0))
