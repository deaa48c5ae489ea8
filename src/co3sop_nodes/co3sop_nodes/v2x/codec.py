"""Payload codecs for voxel features and semantic label grids (ROS-free).

The encoded dataclasses mirror the co3sop_msgs fields one to one (see
VoxelFeatures.msg and SemanticOccupancy.msg for the byte layouts), so the node
glue only copies fields. Decoding checks every declared size against the grid
and a configurable limit *before* decompressing, so a hostile or broken sender
cannot make a receiver allocate more than it accepts.

Feature volumes: (C, nx, ny, nz) float32 -> float32 / float16 / int8 or int4
(two per byte) with a per-row affine scale, dense or sparse (top-k voxels by confidence, all
voxels at or above a confidence threshold, or the voxels a requesting ego needs
most: confidence x its request, Where2comm-style), optionally transform coded
(`rank` K: the K principal directions of the voxels' features, those selected
or, under a budget, every candidate; computed per message and sent with it, and K coefficients per voxel instead of C
channels), or a learned code (`learned`: the model's own K integers per voxel,
model/wire.py, sent as they are: no scale, basis or confidence), then zstd, by
default on the values byte-shuffled (`shuffle-zstd`: every value's low byte,
then every next byte, as Blosc's and HDF5's shuffle filter: a float's sign and
exponent bytes repeat and compress, its low mantissa bytes are noise); a byte
budget (`max_bytes`) keeps the best-scored voxels that fit. Labels: uint8
grids, lossless zstd (single bytes: shuffle-zstd is zstd).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np
import zstandard

from co3sop_nodes.common.errors import (
    CodecError,
    CorruptPayloadError,
    NonFiniteError,
    PayloadTooLargeError,
    SizeMismatchError,
    UnknownCodecError,
)
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.kernels.half_float import from_float16, from_float16_planes, to_float16, to_float16_planes

CODECS = ("shuffle-zstd", "zstd", "none")
# zstd on the values byte-shuffled; values of one byte (int8, int4) are their own shuffle and go as zstd
SHUFFLED = "shuffle-zstd"
# each codec's zstd level where the config leaves it at 0: a LiDAR vehicle's float16 volume shuffled at 1 takes 6 %
# fewer bytes than zstd at 3 and 0.56 of its encoding time (shuffled at 3: 1 % fewer still, in 1.7x the time;
# BENCHMARKS.md, "An Intel CPU without bfloat16")
ZSTD_LEVELS = {SHUFFLED: 1, "zstd": 3, "none": 0}
# element types of the values; int4's are packed two per byte on the wire (low nibble first)
FEATURE_DTYPES = {
    "float32": np.dtype("<f4"),
    "float16": np.dtype("<f2"),
    "int8": np.dtype("i1"),
    "int4": np.dtype("i1"),
}
QUANTIZED = ("int8", "int4")  # affine per row: value = q * scale + offset
# float32 values from this magnitude on round to infinity as float16 (halfway between its largest, 65504, and 2^16)
FLOAT16_OVERFLOW = 65520.0
SELECTIONS = ("dense", "topk", "threshold", "request")
# Receivers refuse payloads that declare more uncompressed bytes than this.
DEFAULT_MAX_RAW_BYTES = 256 * 1024 * 1024
# q in [-L, L], symmetric around the row's mid-range
_LEVELS = {"int8": 127, "int4": 7}
# int4's 15 levels span the row's mean +- this many standard deviations (values beyond saturate): spread over
# min..max, a few outliers would leave the bulk of the values two or three levels
_INT4_SPREAD = 3.0


@dataclass(frozen=True)
class FeatureCodecConfig:
    """How a vehicle encodes its feature volume before sending it."""

    dtype: str = "float16"  # "float32" | "float16" | "int8" | "int4"
    selection: str = "dense"  # "dense" | "topk" | "threshold"
    topk: int = 4096  # voxels kept by "topk" (highest confidence, else highest feature norm)
    threshold: float = 0.5  # "threshold" keeps voxels whose confidence is >= this
    codec: str = SHUFFLED  # "shuffle-zstd" | "zstd" | "none" (`wire_codec`: what a message of this dtype says)
    level: int = 0  # zstd level; 0: the codec's own (ZSTD_LEVELS)
    # > 0: "topk" / "request" keep as many of their best-scored voxels as fit this many bytes (payload and
    # quantisation constants), instead of `topk`
    max_bytes: int = 0
    # > max_bytes: max_bytes is the average per message to one receiver and this the most one message may take (a
    # token bucket kept by the sender, v2x/sender_budget.py; encode_features itself caps at max_bytes)
    burst_bytes: int = 0
    # > 0: transform coding, K coefficients per voxel on the message's own K principal directions (PCA of the selected
    # voxels' features, or of every candidate under a budget; the basis travels in the message): fewer bytes per
    # voxel, so more voxels under a budget
    rank: int = 0
    # the features are a model's learned wire code (K integers per voxel in int4's or int8's range, model/wire.py),
    # sent as they are: the receiver decodes them with the same code's decoder, which also gives the confidence
    learned: bool = False
    # "request" with max_bytes: what the budget leaves after every voxel an ego asked for goes to the others, the
    # most confident first (else a budget the requests do not fill is left unspent)
    fill: bool = False

    def __post_init__(self) -> None:
        check_choice("feature dtype", self.dtype, FEATURE_DTYPES)
        check_choice("feature selection", self.selection, SELECTIONS)
        check_choice("codec", self.codec, CODECS)
        if isinstance(self.topk, bool) or not isinstance(self.topk, numbers.Integral) or self.topk < 1:
            raise CodecError(f"topk must be a whole number of voxels >= 1, got {self.topk!r}")
        if not isinstance(self.threshold, numbers.Real) or not 0.0 <= self.threshold <= 1.0:
            raise CodecError(f"threshold must be a confidence in [0, 1], got {self.threshold!r}")
        if isinstance(self.max_bytes, bool) or not isinstance(self.max_bytes, numbers.Integral) or self.max_bytes < 0:
            raise CodecError(f"max_bytes must be a whole number of bytes >= 0 (0: no budget), got {self.max_bytes!r}")
        if self.max_bytes and self.selection not in ("topk", "request"):
            raise CodecError(f"max_bytes needs selection 'topk' or 'request', not {self.selection!r}")
        if (
            isinstance(self.burst_bytes, bool)
            or not isinstance(self.burst_bytes, numbers.Integral)
            or self.burst_bytes < 0
        ):
            raise CodecError(
                f"burst_bytes must be a whole number of bytes >= 0 (0: every message capped at max_bytes), "
                f"got {self.burst_bytes!r}"
            )
        if self.burst_bytes and (not self.max_bytes or self.burst_bytes < self.max_bytes):
            raise CodecError(
                f"burst_bytes {self.burst_bytes} needs a max_bytes budget of at most it (max_bytes {self.max_bytes})"
            )
        if isinstance(self.rank, bool) or not isinstance(self.rank, numbers.Integral) or self.rank < 0:
            raise CodecError(
                f"rank must be a whole number of components >= 0 (0: the channels as they are), got {self.rank!r}"
            )
        if not isinstance(self.learned, bool):
            raise CodecError(f"learned must be true or false, got {self.learned!r}")
        if not isinstance(self.fill, bool):
            raise CodecError(f"fill must be true or false, got {self.fill!r}")
        if self.fill and not (self.selection == "request" and self.max_bytes):
            raise CodecError(
                f"fill needs selection 'request' and a max_bytes budget (got {self.selection!r}, {self.max_bytes})"
            )
        if self.learned and (self.dtype not in QUANTIZED or self.rank):
            raise CodecError(
                f"learned: the code's integers go as int4 or int8 with no rank (got dtype {self.dtype!r}, "
                f"rank {self.rank})"
            )

    @property
    def name(self) -> str:
        """Short label, e.g. 'float16-topk4096-zstd'."""
        count = f"{self.max_bytes // 1024}KB" if self.max_bytes else str(self.topk)
        if self.burst_bytes:
            count += f"-burst{self.burst_bytes // 1024}KB"
        sel = {
            "dense": "dense",
            "topk": f"topk{count}",
            "threshold": f"conf{self.threshold:g}",
            "request": f"request{count}" + ("-fill" if self.fill else ""),
        }[self.selection]
        transform = f"-pca{self.rank}" if self.rank else "-learned" if self.learned else ""
        return f"{self.dtype}-{sel}{transform}-{self.wire_codec}"

    @property
    def wire_codec(self) -> str:
        """The codec the messages say (`payload_codec`: int8 and int4 values, one byte each, confidence too, go as
        zstd where the config says shuffle-zstd)."""
        return payload_codec(self.codec, FEATURE_DTYPES[self.dtype].itemsize)

    @property
    def zstd_level(self) -> int:
        return resolved_level(self.wire_codec, self.level)


def payload_codec(codec: str, element_bytes: int) -> str:
    """The codec a payload of `element_bytes`-byte elements goes as: `codec`, but zstd for shuffle-zstd of single
    bytes (their own shuffle)."""
    return "zstd" if codec == SHUFFLED and element_bytes == 1 else codec


def resolved_level(codec: str, level: int) -> int:
    """`level`, or where it is 0 `codec`'s own (ZSTD_LEVELS)."""
    return level or ZSTD_LEVELS[codec]


@dataclass(frozen=True)
class EncodedFeatures:
    """A feature volume as carried by co3sop_msgs/VoxelFeatures (minus header and pose)."""

    grid: GridSpec
    channels: int
    dtype: str
    codec: str
    quant_scale: tuple[float, ...]  # int8 / int4 only, one per row of values (C, or K with a basis)
    quant_offset: tuple[float, ...]  # int8 / int4 only, as quant_scale
    sparse: bool
    num_voxels: int
    has_confidence: bool
    voxel_mask: bytes
    values: bytes
    confidence: bytes
    voxel_mask_raw_size: int
    values_raw_size: int
    confidence_raw_size: int
    basis_rank: int = 0  # K > 0: values carry K coefficients per voxel; feature = basis @ coefficients + basis_mean
    basis: tuple[float, ...] = ()  # K > 0 only: (C, K) row-major
    basis_mean: tuple[float, ...] = ()  # K > 0 only: (C,)
    learned_code: str = ""  # a learned code's name: values carry its `channels` integers per voxel, as they are

    @property
    def rows(self) -> int:
        """Rows of the values array: the channels, or the basis's K coefficients."""
        return self.basis_rank or self.channels

    @property
    def payload_bytes(self) -> int:
        """Compressed bytes of all payloads."""
        return len(self.voxel_mask) + len(self.values) + len(self.confidence)

    @property
    def raw_bytes(self) -> int:
        """Uncompressed bytes of all payloads."""
        return self.voxel_mask_raw_size + self.values_raw_size + self.confidence_raw_size

    @property
    def budget_bytes(self) -> int:
        """What a byte budget counts: the payloads, the quantisation constants and the basis (float32 each)."""
        return self.payload_bytes + 4 * (
            len(self.quant_scale) + len(self.quant_offset) + len(self.basis) + len(self.basis_mean)
        )


@dataclass(frozen=True)
class DecodedFeatures:
    features: np.ndarray  # (C, nx, ny, nz) float32 (a learned code's integers: (K, nx, ny, nz)); 0 where not carried
    confidence: np.ndarray | None  # (nx, ny, nz) float32 in [0, 1]; 0 where not carried
    mask: np.ndarray  # (nx, ny, nz) bool: voxels carried
    learned_code: str = ""  # features hold this learned code's integers, for its decoder


@dataclass(frozen=True)
class EncodedLabels:
    """A label grid as carried by co3sop_msgs/SemanticOccupancy (minus header)."""

    grid: GridSpec
    num_classes: int
    codec: str
    labels: bytes
    labels_raw_size: int
    confidence: bytes
    confidence_raw_size: int

    @property
    def payload_bytes(self) -> int:
        return len(self.labels) + len(self.confidence)

    @property
    def raw_bytes(self) -> int:
        return self.labels_raw_size + self.confidence_raw_size


@dataclass(frozen=True)
class DecodedLabels:
    labels: np.ndarray  # (nx, ny, nz) uint8
    confidence: np.ndarray | None  # (nx, ny, nz) uint8, 255 * probability


def check_choice(what: str, value: str, known) -> None:
    if value not in known:
        raise UnknownCodecError(f"unknown {what} {value!r} (known: {', '.join(known)})")


# zstd's match-finder tables at most 2^12 entries (16 KB each, within a core's cache) instead of its defaults for a
# megabyte input (2^17 and 2^16 at level 3): feature volumes, label grids and scans repeat little at long range, and
# the small tables compress them as well or a little better, 10-15 % faster (BENCHMARKS.md, "zstd's tables")
TABLE_LOG = 12


def compress_payload(raw: bytes, codec: str, level: int) -> bytes:
    """raw (already byte-shuffled where `codec` shuffles it: see _wire_bytes) compressed by `codec`."""
    if codec == "none" or not raw:
        return bytes(raw)
    # The content size lets a receiver check the frame before decompressing;
    # the checksum catches corruption inside blocks stored raw.
    return zstandard.ZstdCompressor(compression_params=_zstd_parameters(level, len(raw))).compress(raw)


def _zstd_parameters(level: int, size: int) -> zstandard.ZstdCompressionParameters:
    """`level`'s parameters for a payload of `size` bytes, its tables capped at TABLE_LOG."""
    chosen = zstandard.ZstdCompressionParameters.from_level(level, source_size=size)
    return zstandard.ZstdCompressionParameters(
        window_log=chosen.window_log,
        hash_log=min(chosen.hash_log, TABLE_LOG),
        chain_log=min(chosen.chain_log, TABLE_LOG),
        search_log=chosen.search_log,
        min_match=chosen.min_match,
        target_length=chosen.target_length,
        strategy=chosen.strategy,
        write_checksum=1,
        write_content_size=1,
    )


def decompress_payload(payload, codec: str, declared: int, expected: int, field: str, max_raw_bytes: int) -> bytes:
    """Checks `declared` against the limit and the grid, then decompresses exactly that much."""
    check_choice("codec", codec, CODECS)
    if declared > max_raw_bytes:
        raise PayloadTooLargeError(
            f"{field}: declares {declared} uncompressed bytes, over the receiver's limit of {max_raw_bytes}"
        )
    if declared != expected:
        raise SizeMismatchError(f"{field}: declares {declared} uncompressed bytes but the grid needs {expected}")
    if codec == "none" or expected == 0:
        if len(payload) != expected:
            raise SizeMismatchError(f"{field}: carries {len(payload)} bytes but the grid needs {expected}")
        return bytes(payload)
    try:
        # zstandard trusts the frame's own content size over max_output_size:
        # check it before any output is allocated.
        frame = zstandard.get_frame_parameters(payload)
        if frame.content_size != expected:
            raise CorruptPayloadError(
                f"{field}: zstd frame declares {frame.content_size} bytes; the grid needs {expected}"
            )
        if not frame.has_checksum:
            raise CorruptPayloadError(f"{field}: zstd frame has no checksum (corruption would go unnoticed)")
        raw = zstandard.ZstdDecompressor().decompress(payload, max_output_size=expected, allow_extra_data=False)
    except zstandard.ZstdError as exc:
        raise CorruptPayloadError(f"{field}: truncated or corrupt zstd payload ({exc})") from None
    if len(raw) != expected:
        raise CorruptPayloadError(f"{field}: decompressed to {len(raw)} bytes, expected {expected}")
    return raw


def _score(features: np.ndarray, confidence: np.ndarray | None, request: np.ndarray | None) -> np.ndarray:
    """(V,) how much each voxel is worth sending: confidence x the ego's request ("request" with one), confidence,
    or the feature L2 norm when there is no confidence."""
    if confidence is not None:
        return confidence.reshape(-1) * request.reshape(-1) if request is not None else confidence.reshape(-1)
    return np.linalg.norm(features.reshape(features.shape[0], -1).astype(np.float64), axis=0)  # float64: no overflow


def _select(
    features: np.ndarray, confidence: np.ndarray | None, cfg: FeatureCodecConfig, request: np.ndarray | None
) -> np.ndarray | None:
    """Flat indices (ascending) of the voxels to send, or None for dense ("topk" / "request" without a budget);
    `request` is None unless the selection is "request"."""
    if cfg.selection == "dense":
        return None
    if cfg.selection == "threshold":
        if confidence is None:
            raise CodecError("feature selection 'threshold' needs a confidence volume")
        return np.flatnonzero(confidence.reshape(-1) >= cfg.threshold)
    score = _score(features, confidence, request)
    if cfg.topk >= score.size:
        return np.arange(score.size)
    return np.sort(np.argpartition(-score, cfg.topk - 1)[: cfg.topk])


def _quantize(values: np.ndarray, dtype: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-row affine int8 / int4 (q int8 in [-L, L]): value ~= q * scale + offset, |error| <= scale / 2 within the
    quantised range (int8: min..max; int4: mean +- _INT4_SPREAD standard deviations, clipped to min..max)."""
    # values: (R, N) float32
    levels = _LEVELS[dtype]
    if values.shape[1] == 0:
        zeros = np.zeros(values.shape[0], np.float32)
        return values.astype(np.int8), zeros, zeros
    x = values.astype(np.float64)
    lo, hi = x.min(axis=1), x.max(axis=1)  # (R,)
    if dtype == "int4":
        mean, spread = x.mean(axis=1), _INT4_SPREAD * x.std(axis=1)
        lo, hi = np.maximum(lo, mean - spread), np.minimum(hi, mean + spread)
    offset = ((hi + lo) / 2).astype(np.float32)  # (R,)
    scale = ((hi - lo) / (2 * levels)).astype(np.float32)  # (R,)
    safe = np.where(scale > 0, scale, 1).astype(np.float64)
    q = np.rint((x - offset[:, None].astype(np.float64)) / safe[:, None])
    return np.clip(q, -levels, levels).astype(np.int8), scale, offset


def _values_raw_size(dtype: str, count: int) -> int:
    """Bytes of `count` values of `dtype` on the wire."""
    return -(-count // 2) if dtype == "int4" else count * FEATURE_DTYPES[dtype].itemsize


def _pack_int4(q: np.ndarray) -> bytes:
    """int8 values in [-8, 7] (flat order) -> two per byte, the first in the low nibble."""
    nibbles = q.reshape(-1).view(np.uint8) & 0xF  # two's complement: the low 4 bits
    if nibbles.size % 2:
        nibbles = np.append(nibbles, np.uint8(0))
    return (nibbles[0::2] | (nibbles[1::2] << 4)).tobytes()


def _unpack_int4(raw: bytes, count: int) -> np.ndarray:
    """Inverse of _pack_int4: (count,) int8 in [-8, 7]."""
    packed = np.frombuffer(raw, np.uint8)
    nibbles = np.empty(2 * packed.size, np.uint8)
    nibbles[0::2], nibbles[1::2] = packed & 0xF, packed >> 4
    return (nibbles[:count].view(np.int8) ^ 8) - 8  # two's complement of 4 bits


def _confidence_dtype(dtype: str) -> np.dtype:
    return np.dtype("u1") if dtype in QUANTIZED else FEATURE_DTYPES[dtype]


def encode_features(
    features: np.ndarray,
    confidence: np.ndarray | None,
    grid: GridSpec,
    cfg: FeatureCodecConfig,
    request: np.ndarray | None = None,
    learned_code: str = "",
) -> EncodedFeatures:
    """Encodes a (C, nx, ny, nz) float volume and optional (nx, ny, nz) confidence in [0, 1].

    request: (nx, ny, nz) in [0, 1], how much a requesting ego needs each voxel, in this volume's frame
    (selection "request"; without one it falls back to the confidence alone, as "topk").
    With cfg.max_bytes the result is the largest set of best-scored voxels whose budget_bytes fit.
    With cfg.learned the volume is the code named `learned_code` (K, nx, ny, nz), integers in the dtype's range;
    the confidence then only chooses voxels (the code carries it).
    """
    features = np.asarray(features, dtype=np.float32)
    if features.ndim != 4 or features.shape[1:] != grid.dims or features.shape[0] < 1:
        raise SizeMismatchError(
            f"features: shape {features.shape} does not match (C, {', '.join(map(str, grid.dims))})"
        )
    # the extremes, two passes without a temporary: NaN makes them NaN, and they bound |x|
    low, high = (float(features.min()), float(features.max())) if features.size else (0.0, 0.0)
    if not (np.isfinite(low) and np.isfinite(high)):
        raise CodecError("features: contain NaN or infinite values")
    if cfg.dtype == "float16" and max(-low, high) >= FLOAT16_OVERFLOW:
        raise CodecError("features: values beyond the float16 range (|x| > 65504); use float32 or int8")
    if cfg.learned:
        _check_code(features, cfg.dtype, learned_code)
    elif learned_code:
        raise CodecError(f"learned_code {learned_code!r} given to a codec that is not learned")
    if confidence is not None:
        confidence = np.asarray(confidence, dtype=np.float32)
        if confidence.shape != grid.dims:
            raise SizeMismatchError(f"confidence: shape {confidence.shape} does not match the grid {grid.dims}")
        if not (np.isfinite(confidence).all() and confidence.min() >= 0 and confidence.max() <= 1):
            raise CodecError("confidence: values must lie in [0, 1]")
    if cfg.selection != "request":
        request = None  # only "request" weighs by it
    if request is not None:
        request = np.asarray(request, dtype=np.float32)
        if request.shape != grid.dims or not (np.isfinite(request).all() and request.min() >= 0 and request.max() <= 1):
            raise CodecError(f"request: a (nx, ny, nz) = {grid.dims} volume in [0, 1] expected")
    if cfg.max_bytes:
        return _within_budget(features, confidence, grid, cfg, request, learned_code)
    keep = _select(features, confidence, cfg, request)
    return _encode(features, confidence, grid, cfg, keep, _basis(features, keep, cfg.rank), learned_code)


def _check_code(code: np.ndarray, dtype: str, name: str) -> None:
    """A learned code's values are its integers, within what `dtype` carries."""
    if not name:
        raise CodecError("learned: the code's name (learned_code) is missing")
    levels = _LEVELS[dtype]
    if code.size and (np.abs(code).max() > levels or not np.array_equal(code, np.rint(code))):
        raise CodecError(f"features: a learned code's values must be integers in [-{levels}, {levels}] for {dtype}")


def check_codec_for(cfg: FeatureCodecConfig, channels: int, grid: GridSpec) -> None:
    """Refuses (CodecError) a codec that could encode no message of `channels` x `grid` features: a rank above
    the channels, a byte budget below the smallest message (an empty selection with its header and constants)."""
    if cfg.rank > channels:
        raise CodecError(f"rank {cfg.rank}: more components than the {channels} feature channels")
    if cfg.max_bytes:
        zeros = np.zeros((channels, *grid.dims), np.float32)
        none = np.zeros(0, np.int64)
        smallest = _encode(zeros, zeros[0], grid, cfg, none, _basis(zeros, none, cfg.rank)).budget_bytes
        if smallest > cfg.max_bytes:
            raise CodecError(f"max_bytes {cfg.max_bytes}: even an empty selection takes {smallest} bytes")


# the count of a budget's search is settled to 1 / 2**SIZE_NOISE_SHIFT of itself: compression noise on the size
# (tens of bytes: a count of 5,000 voxels may fit where one of 4,990 does not) makes a finer search tries for nothing
SIZE_NOISE_SHIFT = 8


def _within_budget(
    features, confidence, grid: GridSpec, cfg: FeatureCodecConfig, request, learned_code: str
) -> EncodedFeatures:
    """The most best-scored voxels whose encoding fits cfg.max_bytes: a count that fits while one more (or,
    beyond 256 voxels, 0.4 % more) does not; the size grows with the count up to compression noise, so this is
    within a few voxels of the largest. Each try costs a compression, so all candidates are tried first (under a
    request map they often fit) and the count is then found by regula falsi, Illinois' variant, on the sizes (nearly
    linear in the count: a handful of tries where bisection takes log2 of the candidates), bisecting where it
    stalls."""
    score = _score(features, confidence, request)
    order = np.argsort(-score, kind="stable")
    if request is not None:
        asked, rest = np.split(order, [np.count_nonzero(score > 0)])
        if cfg.fill:  # then what no ego asked for, the sender's most confident first
            order = np.concatenate([asked, rest[np.argsort(-_score(features, confidence, None)[rest], kind="stable")]])
        else:  # what the ego did not ask for is not worth a byte
            order = asked

    basis = _basis(features, np.sort(order), cfg.rank)  # one for every count tried: that of all candidates

    def encoded(k: int) -> EncodedFeatures:
        return _encode(features, confidence, grid, cfg, np.sort(order[:k]), basis, learned_code)

    best = encoded(0)
    if best.budget_bytes > cfg.max_bytes:
        raise CodecError(f"max_bytes {cfg.max_bytes}: even an empty selection takes {best.budget_bytes} bytes")
    if not len(order):
        return best
    enc = encoded(len(order))
    if enc.budget_bytes <= cfg.max_bytes:
        return enc
    # lo fits, over does not; below / above: their sizes less the budget (Illinois halves the one kept twice)
    lo, over = 0, len(order)
    below, above = best.budget_bytes - cfg.max_bytes, enc.budget_bytes - cfg.max_bytes
    kept, tries = None, 2 * max(1, len(order)).bit_length()
    while over - lo > max(1, lo >> SIZE_NOISE_SHIFT):
        tries -= 1
        if tries < 0:  # stalled: bisection bounds what is left
            k = (lo + over) // 2
        else:
            k = min(max(lo + int(-below * (over - lo) / (above - below)), lo + 1), over - 1)
        enc = encoded(k)
        if enc.budget_bytes <= cfg.max_bytes:
            lo, best, below = k, enc, enc.budget_bytes - cfg.max_bytes
            above = above / 2 if kept == "over" else above
            kept = "over"
        else:
            over, above = k, enc.budget_bytes - cfg.max_bytes
            below = below / 2 if kept == "lo" else below
            kept = "lo"
    return best


def _encode(
    features: np.ndarray,
    confidence: np.ndarray | None,
    grid: GridSpec,
    cfg: FeatureCodecConfig,
    keep: np.ndarray | None,
    basis: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    learned_code: str = "",
) -> EncodedFeatures:
    """keep: flat indices of the voxels sent (None: all); basis: _basis's transform coding, to send the voxels as
    its K coefficients, or None for the channels themselves; with cfg.learned the features are the integers of the
    code `learned_code`, sent as they are (no constants, no confidence)."""
    channels = features.shape[0]
    sent_basis = sent_mean = ()
    if basis is None:
        flat = features.reshape(channels, -1)  # (C, V)
        values = flat if keep is None else flat[:, keep]  # (C, N)
    else:
        directions, mean, coefficients = basis
        values = coefficients if keep is None else coefficients[:, keep]  # (K, N)
        sent_basis, sent_mean = tuple(directions.reshape(-1).tolist()), tuple(mean.tolist())
        if cfg.dtype == "float16" and values.size and np.abs(values).max() >= FLOAT16_OVERFLOW:
            raise CodecError("features: coefficients beyond the float16 range (|x| > 65504); use float32 or int8")
    num_voxels = values.shape[1]

    mask_raw = b""
    if keep is not None:
        bits = np.zeros(grid.num_voxels, dtype=bool)
        bits[keep] = True
        mask_raw = np.packbits(bits, bitorder="little").tobytes()

    scale = offset = ()
    codec, level = cfg.wire_codec, cfg.zstd_level
    shuffled = codec == SHUFFLED
    if cfg.learned:
        q = values.astype(np.int8)
        values_raw = _pack_int4(q) if cfg.dtype == "int4" else q.tobytes()
        confidence = None  # the code carries it
    elif cfg.dtype in QUANTIZED:
        q, s, o = _quantize(values, cfg.dtype)
        values_raw = _pack_int4(q) if cfg.dtype == "int4" else q.tobytes()
        scale, offset = tuple(s.tolist()), tuple(o.tolist())
    else:
        values_raw = _wire_bytes(values, cfg.dtype, shuffled)

    conf_raw = b""
    if confidence is not None:
        conf = confidence.reshape(-1) if keep is None else confidence.reshape(-1)[keep]  # (N,)
        if cfg.dtype in QUANTIZED:
            conf_raw = np.rint(conf * 255).astype(np.uint8).tobytes()
        else:
            conf_raw = _wire_bytes(conf, cfg.dtype, shuffled)

    return EncodedFeatures(
        grid=grid,
        channels=channels,
        dtype=cfg.dtype,
        codec=codec,
        quant_scale=scale,
        quant_offset=offset,
        sparse=keep is not None,
        num_voxels=num_voxels,
        has_confidence=confidence is not None,
        voxel_mask=compress_payload(mask_raw, codec, level),
        values=compress_payload(values_raw, codec, level),
        confidence=compress_payload(conf_raw, codec, level),
        voxel_mask_raw_size=len(mask_raw),
        values_raw_size=len(values_raw),
        confidence_raw_size=len(conf_raw),
        basis_rank=0 if basis is None else basis[0].shape[1],
        basis=sent_basis,
        basis_mean=sent_mean,
        learned_code=learned_code,
    )


def _basis(
    features: np.ndarray, keep: np.ndarray | None, rank: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The transform coding fitted to the voxels `keep` (None: all): their K = rank principal directions, (C, K)
    float32 with orthonormal columns (largest variance first, each column's largest entry positive), their mean
    (C,) float32, and every voxel's coefficients (K, V) float32, the least-squares ones on the float32 basis the
    receiver gets; None when rank is 0. Under a byte budget it is fitted once to every candidate voxel."""
    if not rank:
        return None
    channels = features.shape[0]
    if rank > channels:
        raise CodecError(f"rank {rank}: more components than the {channels} feature channels")
    flat = features.reshape(channels, -1)
    x = (flat if keep is None else flat[:, keep]).astype(np.float64)  # (C, N)
    mean = (x.mean(axis=1) if x.shape[1] else np.zeros(channels)).astype(np.float32)
    centred = x - mean[:, None]
    # einsum, not `@`: numpy's own single-threaded loops. A multithreaded BLAS spinning in each of several vehicle
    # processes on a few cores made encoding 10-100x slower in the graph; the bits also no longer depend on threads.
    _, vectors = np.linalg.eigh(np.einsum("cn,dn->cd", centred, centred))  # ascending eigenvalues
    directions = vectors[:, ::-1][:, :rank]  # (C, K)
    directions *= np.where(directions[np.abs(directions).argmax(axis=0), np.arange(rank)] < 0, -1.0, 1.0)
    directions = directions.astype(np.float32)
    coefficients = np.einsum(
        "ck,cv->kv", directions.astype(np.float64), flat - mean[:, None].astype(np.float64)
    )  # (K, V)
    return directions, mean, coefficients.astype(np.float32)


def _wire_bytes(values: np.ndarray, dtype: str, shuffled: bool) -> bytes:
    """float32 values as the float dtype on the wire (float32 or float16), C order; `shuffled`: byte-shuffled
    (every value's byte 0, then every value's byte 1, ...)."""
    if dtype == "float16":
        return (to_float16_planes(values) if shuffled else to_float16(values)).tobytes()
    wire = np.ascontiguousarray(values, FEATURE_DTYPES[dtype])
    return (
        np.ascontiguousarray(wire.view(np.uint8).reshape(-1, wire.itemsize).T).tobytes() if shuffled else wire.tobytes()
    )


def _from_wire(raw: bytes, dtype: np.dtype, shuffled: bool) -> np.ndarray:
    """`_wire_bytes`' inverse, and integers as they are: raw -> (n,) float32."""
    if shuffled and dtype.itemsize > 1:
        planes = np.frombuffer(raw, np.uint8)
        if dtype == np.float16:
            return from_float16_planes(planes)
        return np.ascontiguousarray(planes.reshape(dtype.itemsize, -1).T).view(dtype).reshape(-1).astype(np.float32)
    values = np.frombuffer(raw, dtype)
    return from_float16(values) if values.dtype == np.float16 else values.astype(np.float32)


def _check_finite(field: str, values: np.ndarray) -> None:
    """One faulty sender must not poison a fused map: NaN or inf anywhere drops the whole message."""
    bad = ~np.isfinite(values)
    if bad.any():
        raise NonFiniteError(f"{field}: {int(bad.sum())} NaN or infinite value(s) of {values.size}")


def decode_features(enc: EncodedFeatures, max_raw_bytes: int = DEFAULT_MAX_RAW_BYTES) -> DecodedFeatures:
    """Inverse of encode_features; raises a CodecError subclass naming the bad field."""
    check_choice("feature dtype", enc.dtype, FEATURE_DTYPES)
    check_choice("codec", enc.codec, CODECS)
    grid, channels = enc.grid, enc.channels
    if channels < 1:
        raise SizeMismatchError(f"channels: must be at least 1, got {channels}")
    if enc.sparse:
        mask_raw = decompress_payload(
            enc.voxel_mask, enc.codec, enc.voxel_mask_raw_size, -(-grid.num_voxels // 8), "voxel_mask", max_raw_bytes
        )
        bits = np.unpackbits(np.frombuffer(mask_raw, np.uint8), count=grid.num_voxels, bitorder="little").astype(bool)
        if int(bits.sum()) != enc.num_voxels:
            raise SizeMismatchError(f"num_voxels: declares {enc.num_voxels} but voxel_mask selects {int(bits.sum())}")
    else:
        if enc.num_voxels != grid.num_voxels:
            raise SizeMismatchError(f"num_voxels: declares {enc.num_voxels} for a dense grid of {grid.num_voxels}")
        bits = None
    n, rows = enc.num_voxels, enc.rows
    if not 0 <= enc.basis_rank <= channels:
        raise SizeMismatchError(f"basis_rank: {enc.basis_rank} components for {channels} channels")
    if len(enc.basis) != channels * enc.basis_rank or len(enc.basis_mean) != (channels if enc.basis_rank else 0):
        raise SizeMismatchError(
            f"basis/basis_mean: need {channels * enc.basis_rank}/{channels if enc.basis_rank else 0} entries for "
            f"basis_rank {enc.basis_rank}, got {len(enc.basis)}/{len(enc.basis_mean)}"
        )
    if enc.learned_code:
        _check_learned(enc)
    raw = decompress_payload(
        enc.values, enc.codec, enc.values_raw_size, _values_raw_size(enc.dtype, rows * n), "values", max_raw_bytes
    )
    shuffled = enc.codec == SHUFFLED
    if enc.dtype == "int4":
        values = _unpack_int4(raw, rows * n).astype(np.float32).reshape(rows, n)
    else:
        values = _from_wire(raw, FEATURE_DTYPES[enc.dtype], shuffled).reshape(rows, n)  # (C, N), (K, N) or a code
    if enc.learned_code:
        levels = _LEVELS[enc.dtype]
        if n and np.abs(values).max() > levels:
            raise CodecError(f"values: a learned code's integers lie in [-{levels}, {levels}] for {enc.dtype}")
    elif enc.dtype in QUANTIZED:
        if len(enc.quant_scale) != rows or len(enc.quant_offset) != rows:
            raise SizeMismatchError(
                f"quant_scale/quant_offset: need {rows} entries each, got "
                f"{len(enc.quant_scale)}/{len(enc.quant_offset)}"
            )
        scale = np.asarray(enc.quant_scale, np.float32).astype(np.float64)[:, None]
        offset = np.asarray(enc.quant_offset, np.float32).astype(np.float64)[:, None]
        _check_finite("quant_scale", scale)
        _check_finite("quant_offset", offset)
        # float64 then clip: q * scale + offset may round past float32's range
        f32max = np.finfo(np.float32).max
        values = np.clip(values * scale + offset, -f32max, f32max).astype(np.float32)
    else:
        _check_finite("values", values)
    if enc.basis_rank:
        basis = np.asarray(enc.basis, np.float32).reshape(channels, enc.basis_rank).astype(np.float64)
        mean = np.asarray(enc.basis_mean, np.float32).astype(np.float64)[:, None]
        _check_finite("basis", basis)
        _check_finite("basis_mean", mean)
        f32max = np.finfo(np.float32).max
        rebuilt = np.einsum("ck,kn->cn", basis, values) + mean  # (C, N); einsum, not BLAS threads: see _basis
        values = np.clip(rebuilt, -f32max, f32max).astype(np.float32)

    conf = None  # (N,) float32
    if enc.has_confidence:
        cdtype = _confidence_dtype(enc.dtype)
        craw = decompress_payload(
            enc.confidence, enc.codec, enc.confidence_raw_size, n * cdtype.itemsize, "confidence", max_raw_bytes
        )
        conf = _from_wire(craw, cdtype, shuffled)
        if enc.dtype in QUANTIZED:
            conf = conf / np.float32(255)
        else:
            _check_finite("confidence", conf)
            if conf.size and not (conf.min() >= 0 and conf.max() <= 1):
                raise CodecError(f"confidence: values must lie in [0, 1], got [{conf.min():g}, {conf.max():g}]")
    elif enc.confidence or enc.confidence_raw_size:
        raise SizeMismatchError("confidence: payload present but has_confidence is false")
    if bits is None:
        features = values.reshape(channels, *grid.dims)
        confidence = None if conf is None else conf.reshape(grid.dims)
        mask = np.ones(grid.dims, dtype=bool)
    else:
        features = np.zeros((channels, grid.num_voxels), np.float32)
        features[:, bits] = values
        features = features.reshape(channels, *grid.dims)
        confidence = None
        if conf is not None:
            confidence = np.zeros(grid.num_voxels, np.float32)
            confidence[bits] = conf
            confidence = confidence.reshape(grid.dims)
        mask = bits.reshape(grid.dims)
    return DecodedFeatures(features=features, confidence=confidence, mask=mask, learned_code=enc.learned_code)


def _check_learned(enc: EncodedFeatures) -> None:
    """A learned code's message has its integers only: no quantisation constants, basis or confidence."""
    if enc.dtype not in QUANTIZED:
        raise CodecError(f"dtype: a learned code goes as int4 or int8, not {enc.dtype!r}")
    if len(enc.learned_code) > 64:
        raise CodecError(f"learned_code: a name of {len(enc.learned_code)} characters (at most 64)")
    for field, value in (
        ("quant_scale", enc.quant_scale),
        ("quant_offset", enc.quant_offset),
        ("basis", enc.basis),
        ("basis_mean", enc.basis_mean),
    ):
        if value:
            raise SizeMismatchError(f"{field}: must be empty with a learned code, got {len(value)} entries")
    if enc.basis_rank:
        raise SizeMismatchError(f"basis_rank: must be 0 with a learned code, got {enc.basis_rank}")
    if enc.has_confidence:
        raise SizeMismatchError("has_confidence: a learned code carries its own confidence, must be false")


def encode_labels(
    labels: np.ndarray,
    grid: GridSpec,
    num_classes: int,
    confidence: np.ndarray | None = None,
    codec: str = "zstd",
    level: int = 1,
) -> EncodedLabels:
    """Encodes an (nx, ny, nz) uint8 label grid and optional uint8 confidence (255 * p). zstd's fastest level by
    default: on a 51.2 m prediction, labels and confidence take within 5 % of level 3's bytes in 70 % of its time."""
    check_choice("codec", codec, CODECS)
    labels = np.asarray(labels)
    if labels.shape != grid.dims:
        raise SizeMismatchError(f"labels: shape {labels.shape} does not match the grid {grid.dims}")
    if labels.dtype != np.uint8:
        raise CodecError(f"labels: dtype must be uint8, got {labels.dtype}")
    _check_labels(labels, num_classes)
    raw = np.ascontiguousarray(labels).tobytes()
    conf_raw = b""
    if confidence is not None:
        confidence = np.asarray(confidence)
        if confidence.shape != grid.dims or confidence.dtype != np.uint8:
            raise SizeMismatchError(
                f"confidence: need uint8 of shape {grid.dims}, got {confidence.dtype} {confidence.shape}"
            )
        conf_raw = np.ascontiguousarray(confidence).tobytes()
    return EncodedLabels(
        grid=grid,
        num_classes=num_classes,
        codec=codec,
        labels=compress_payload(raw, codec, level),
        labels_raw_size=len(raw),
        confidence=compress_payload(conf_raw, codec, level),
        confidence_raw_size=len(conf_raw),
    )


def _check_labels(labels: np.ndarray, num_classes: int) -> None:
    """Every label is a class index or the ignore value 255."""
    if not 1 <= num_classes <= 255:
        raise CodecError(f"num_classes: must be in 1..255, got {num_classes}")
    if labels.size == 0 or labels.max() < num_classes:
        return
    counts = np.bincount(labels.reshape(-1), minlength=256)  # (256,)
    counts[255] = 0
    bad = np.flatnonzero(counts[num_classes:]) + num_classes
    if bad.size:
        raise CodecError(f"labels: unknown label value(s) {bad.tolist()} for {num_classes} classes")


def decode_labels(
    enc: EncodedLabels, max_raw_bytes: int = DEFAULT_MAX_RAW_BYTES, with_confidence: bool = True
) -> DecodedLabels:
    """Inverse of encode_labels; raises a CodecError subclass naming the bad field. Without `with_confidence` the
    confidence is neither decompressed nor checked (None): for readers of the labels alone, since a prediction's
    noisy confidence takes several times its labels' time to decompress."""
    n = enc.grid.num_voxels
    raw = decompress_payload(enc.labels, enc.codec, enc.labels_raw_size, n, "labels", max_raw_bytes)
    labels = np.frombuffer(raw, np.uint8).reshape(enc.grid.dims)
    _check_labels(labels, enc.num_classes)
    confidence = None
    if with_confidence and (enc.confidence_raw_size or enc.confidence):
        craw = decompress_payload(enc.confidence, enc.codec, enc.confidence_raw_size, n, "confidence", max_raw_bytes)
        confidence = np.frombuffer(craw, np.uint8).reshape(enc.grid.dims)
    return DecodedLabels(labels=labels, confidence=confidence)


# a request map's levels: need quantized to 2 (a yes or no per voxel) .. 256 (1/255 steps)
REQUEST_LEVELS = (2, 256)


@dataclass(frozen=True)
class EncodedRequest:
    """An ego's request map as carried by co3sop_msgs/RequestMap (minus header, ids and pose)."""

    grid: GridSpec
    codec: str
    need: bytes
    need_raw_size: int
    levels: int = 256


def _check_levels(levels: int) -> None:
    if not REQUEST_LEVELS[0] <= levels <= REQUEST_LEVELS[1]:
        raise CodecError(f"levels: {levels}, expected {REQUEST_LEVELS[0]} to {REQUEST_LEVELS[1]}")


# zstd level of request maps: an ego's map crosses the medium to every vehicle each frame; at 51.2 m level 15 makes
# it about 30 % smaller than level 3 for about 4 ms of the ego's time (level 19: the same bytes, 15 ms)
REQUEST_ZSTD_LEVEL = 15


def encode_request(
    need: np.ndarray, grid: GridSpec, codec: str = "zstd", level: int = REQUEST_ZSTD_LEVEL, levels: int = 256
) -> EncodedRequest:
    """(nx, ny, nz) need in [0, 1] -> round((levels - 1) * need) uint8, compressed (fewer levels, fewer bytes: 2
    levels send whether the need is above a half)."""
    check_choice("codec", codec, CODECS)
    _check_levels(levels)
    need = np.asarray(need, dtype=np.float32)
    if need.shape != grid.dims:
        raise SizeMismatchError(f"need: shape {need.shape} does not match the grid {grid.dims}")
    if not (np.isfinite(need).all() and need.min(initial=0) >= 0 and need.max(initial=0) <= 1):
        raise CodecError("need: values must lie in [0, 1]")
    raw = np.rint(need * (levels - 1)).astype(np.uint8).tobytes()
    return EncodedRequest(grid, codec, compress_payload(raw, codec, level), len(raw), levels)


def decode_request(enc: EncodedRequest, max_raw_bytes: int = DEFAULT_MAX_RAW_BYTES) -> np.ndarray:
    """Inverse of encode_request: (nx, ny, nz) float32 need in [0, 1] (multiples of 1 / (levels - 1))."""
    _check_levels(enc.levels)
    raw = decompress_payload(enc.need, enc.codec, enc.need_raw_size, enc.grid.num_voxels, "need", max_raw_bytes)
    q = np.frombuffer(raw, np.uint8)
    if q.size and q.max() >= enc.levels:
        raise CodecError(f"need: value {q.max()} beyond its {enc.levels} levels")
    return (q.astype(np.float32) / (enc.levels - 1)).reshape(enc.grid.dims)
