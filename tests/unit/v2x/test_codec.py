"""Unit tests for co3sop_nodes.v2x.codec (ROS-free, CPU only, fast).

Round trips are property tests over small random grids for every codec
setting; the wire layout is checked against VoxelFeatures.msg /
SemanticOccupancy.msg with an independent decoder (zstandard + numpy), so a
bug shared by encoder and decoder cannot hide behind a passing round trip.
Every error path has a test asserting the exception type, that it derives
from Co3sopError, and that its message names the field at fault.
"""

from __future__ import annotations

import dataclasses
import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from co3sop_nodes.common.errors import (
    Co3sopError,
    CodecError,
    CorruptPayloadError,
    NonFiniteError,
    PayloadTooLargeError,
    SizeMismatchError,
    UnknownCodecError,
)
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.v2x import codec
from co3sop_nodes.v2x.codec import (
    CODECS,
    DEFAULT_MAX_RAW_BYTES,
    FEATURE_DTYPES,
    SELECTIONS,
    DecodedFeatures,
    DecodedLabels,
    EncodedFeatures,
    EncodedLabels,
    FeatureCodecConfig,
    decode_features,
    decode_labels,
    encode_features,
    encode_labels,
)

MIB = 1024 * 1024
EPS32 = 2.0**-24  # unit round-off of float32
ORIGIN = (-0.4, -0.4, -2.0)

# Feature values: every finite float32 for float32 and int8 (so squares in the
# top-k norm overflow float32, and int8 scales approach float32's limits);
# float16 only within its finite range (encoding beyond it is an error, see
# test_float16_out_of_range_is_an_error).
F16_MAX = float(np.finfo(np.float16).max)  # 65504
FEATURE_ELEMENTS = st.floats(width=32, allow_nan=False, allow_infinity=False)
FLOAT16_ELEMENTS = st.floats(-F16_MAX, F16_MAX, width=32)
CONF_ELEMENTS = st.floats(0.0, 1.0, width=32)

# VoxelFeatures.msg: the wire fields EncodedFeatures mirrors one to one.
MSG_DIR = Path(__file__).resolve().parents[3] / "src" / "co3sop_msgs" / "msg"
VOXEL_FEATURES_ENVELOPE = {
    "header",
    "agent_id",
    "addressed",
    "recipient_id",
    "lidar_pose",
}  # set by the ROS glue, not the codec

# Every valid (dtype, selection, codec) setting; threshold needs a confidence.
ALL_SETTINGS = [
    (dtype, selection, codec_name, with_conf)
    for dtype in FEATURE_DTYPES
    for selection in SELECTIONS
    for codec_name in CODECS
    for with_conf in (False, True)
    if not (selection == "threshold" and not with_conf)
]


def _id(setting):
    dtype, selection, codec_name, with_conf = setting
    return f"{dtype}-{selection}-{codec_name}-{'conf' if with_conf else 'noconf'}"


def _grid(dims) -> GridSpec:
    return GridSpec(ORIGIN, 0.2, dims)


def _assert_error(info, exc_type, *fragments: str) -> None:
    """The raised exception is exactly the documented type, a Co3sopError, and names the field."""
    exc = info.value
    assert type(exc) is exc_type, f"expected {exc_type.__name__}, got {type(exc).__name__}: {exc}"
    assert isinstance(exc, Co3sopError)
    message = str(exc)
    for fragment in fragments:
        assert fragment in message, f"{fragment!r} not in error message {message!r}"


QUANT_LEVELS = {"int8": 127, "int4": 7}  # q in [-L, L]


def _wire_values(values_raw: bytes, dtype: str, rows: int, n: int) -> np.ndarray:
    """Independent reading of the values payload as VoxelFeatures.msg documents it: (rows, n) of dtype's values
    (int4: two per byte, the first in the low nibble, two's complement)."""
    if dtype != "int4":
        return np.frombuffer(values_raw, FEATURE_DTYPES[dtype]).reshape(rows, n)
    packed = np.frombuffer(values_raw, np.uint8)
    assert len(packed) == -(-rows * n // 2)
    nibbles = np.stack([packed & 15, packed >> 4], axis=1).reshape(-1).astype(np.int16)
    assert not (rows * n) % 2 or nibbles[-1] == 0  # padding clear
    return np.where(nibbles >= 8, nibbles - 16, nibbles)[: rows * n].astype(np.int8).reshape(rows, n)


def _quant_range(values: np.ndarray, dtype: str) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) per row of (R, N) float64 values that the quantiser spans: min..max for int8; for int4 the mean
    +- 3 standard deviations within min..max."""
    lo, hi = values.min(axis=1), values.max(axis=1)
    if dtype == "int4":
        mean, spread = values.mean(axis=1), 3 * values.std(axis=1)
        lo, hi = np.maximum(lo, mean - spread), np.minimum(hi, mean + spread)
    return lo, hi


def _raw_field(payload: bytes, codec_name: str, itemsize: int = 1) -> bytes:
    """Independent decompression of one wire payload of `itemsize`-byte elements (not via codec._decompress),
    unshuffled where the codec shuffles: shuffle-zstd sends byte k of every element as plane k."""
    if codec_name == "none" or not payload:
        return payload
    raw = zstandard.ZstdDecompressor().decompress(payload)
    if codec_name == "shuffle-zstd" and itemsize > 1:
        return np.frombuffer(raw, np.uint8).reshape(itemsize, -1).T.tobytes()
    return raw


# ---------------------------------------------------------------------------
# strategies


@st.composite
def feature_volumes(draw, with_confidence: bool, elements=FEATURE_ELEMENTS):
    dims = draw(st.tuples(st.integers(1, 8), st.integers(1, 8), st.integers(1, 8)))
    channels = draw(st.integers(1, 5))
    features = draw(arrays(np.float32, (channels, *dims), elements=elements))
    confidence = draw(arrays(np.float32, dims, elements=CONF_ELEMENTS)) if with_confidence else None
    return _grid(dims), features, confidence


@st.composite
def feature_cases(draw, dtype: str, selection: str, codec_name: str, with_conf: bool):
    elements = FLOAT16_ELEMENTS if dtype == "float16" else FEATURE_ELEMENTS
    grid, features, confidence = draw(feature_volumes(with_conf, elements))
    kwargs = {"dtype": dtype, "selection": selection, "codec": codec_name, "level": draw(st.sampled_from([1, 3]))}
    if selection == "topk":
        # both k < V (a real choice) and k >= V (keeps everything)
        kwargs["topk"] = draw(st.integers(1, grid.num_voxels + 2))
    if selection == "threshold":
        # Thresholds are float32-representable (so "conf >= threshold" has one
        # meaning in float32 and float64); half the time exactly a voxel's
        # confidence, so ties at the threshold are exercised.
        kwargs["threshold"] = draw(st.one_of(CONF_ELEMENTS, st.sampled_from(confidence.ravel().tolist())))
    return grid, features, confidence, FeatureCodecConfig(**kwargs)


# ---------------------------------------------------------------------------
# feature round trip, all settings


def _check_selection(features, confidence, cfg, mask, num_voxels):
    v = mask.size
    channels = features.shape[0]
    if cfg.selection == "dense":
        assert mask.all()
        return
    if cfg.selection == "threshold":
        np.testing.assert_array_equal(mask, confidence.reshape(-1) >= cfg.threshold)
        return
    # top-k
    assert mask.sum() == min(cfg.topk, v) == num_voxels
    if 0 < mask.sum() < v:
        if confidence is not None:
            score = confidence.reshape(-1)
            assert score[mask].min() >= score[~mask].max()
        else:
            # float64 norms: no float32 input can overflow or underflow them,
            # so the ranking is exact up to float64 rounding
            score = np.sqrt((features.reshape(channels, -1).astype(np.float64) ** 2).sum(axis=0))
            assert np.isfinite(score).all()
            assert score[mask].min() >= score[~mask].max() * (1 - 1e-12)


def _check_values(dtype, carried_in, carried_out, enc):
    """carried_*: (C, N) float32 of the carried voxels."""
    assert np.isfinite(carried_out).all(), "finite input must decode to finite values"
    if dtype == "float32":
        np.testing.assert_array_equal(carried_out.view(np.uint32), carried_in.view(np.uint32))  # bit-exact
    elif dtype == "float16":
        expected = carried_in.astype(np.float16).astype(np.float32)
        np.testing.assert_array_equal(carried_out.view(np.uint32), expected.view(np.uint32))
    else:
        channels = carried_in.shape[0]
        assert len(enc.quant_scale) == len(enc.quant_offset) == channels
        scale = np.asarray(enc.quant_scale, np.float64)
        offset = np.asarray(enc.quant_offset, np.float64)
        assert np.all(scale >= 0)
        if carried_in.shape[1] == 0:
            return
        vin = carried_in.astype(np.float64)
        lo, hi = _quant_range(vin, dtype)
        mag = np.maximum(np.abs(lo), np.abs(hi))
        # the scale is as tight as 2L + 1 levels allow over the quantised range (not just "some" scale)...
        assert np.all(scale <= (hi - lo) / (2 * QUANT_LEVELS[dtype]) * (1 + 4 * EPS32) + 1e-44)
        assert np.all(np.abs(offset - (hi + lo) / 2) <= 2 * EPS32 * mag + 1e-44)
        # ...and every carried value is within half a step of its original, brought into that range
        err = np.abs(carried_out.astype(np.float64) - np.clip(vin, lo[:, None], hi[:, None]))
        bound = scale / 2 + 4 * EPS32 * mag + 1e-37
        bad = err > bound[:, None]
        assert not bad.any(), f"{dtype} error {err[bad]} over bound {np.broadcast_to(bound[:, None], err.shape)[bad]}"


def _check_confidence(dtype, conf_in, conf_out):
    """conf_*: (N,) float32 of the carried voxels."""
    if dtype == "float32":
        np.testing.assert_array_equal(conf_out.view(np.uint32), conf_in.view(np.uint32))
    elif dtype == "float16":
        np.testing.assert_array_equal(conf_out, conf_in.astype(np.float16).astype(np.float32))
    else:
        assert np.all(np.abs(conf_out.astype(np.float64) - conf_in) <= 1 / 255 / 2 + 1e-6)


def _check_sizes_and_wire(enc, features, confidence, cfg, mask):
    """Field sizes and byte layouts as VoxelFeatures.msg documents them."""
    channels = features.shape[0]
    v = mask.size
    n = int(mask.sum())
    itemsize = FEATURE_DTYPES[cfg.dtype].itemsize
    quantized = cfg.dtype in QUANT_LEVELS
    assert enc.channels == channels and enc.dtype == cfg.dtype and enc.codec == cfg.wire_codec
    assert enc.codec == ("zstd" if cfg.codec == "shuffle-zstd" and quantized else cfg.codec)
    assert enc.sparse == (cfg.selection != "dense")
    assert enc.num_voxels == n
    assert enc.values_raw_size == (-(-channels * n // 2) if cfg.dtype == "int4" else channels * n * itemsize)
    assert enc.voxel_mask_raw_size == (-(-v // 8) if enc.sparse else 0)
    conf_itemsize = 1 if quantized else itemsize
    # has_confidence: the sender had a confidence volume; then the payload
    # carries one value per carried voxel, even when none is carried
    assert enc.has_confidence is (confidence is not None)
    assert enc.confidence_raw_size == (n * conf_itemsize if enc.has_confidence else 0)
    if not enc.has_confidence:
        assert enc.confidence == b""
    if not quantized:
        assert enc.quant_scale == () and enc.quant_offset == ()
    assert enc.payload_bytes == len(enc.voxel_mask) + len(enc.values) + len(enc.confidence)
    assert enc.raw_bytes == enc.voxel_mask_raw_size + enc.values_raw_size + enc.confidence_raw_size

    mask_raw = _raw_field(enc.voxel_mask, cfg.codec)
    values_raw = _raw_field(enc.values, cfg.codec, FEATURE_DTYPES[cfg.dtype].itemsize)
    conf_raw = _raw_field(enc.confidence, cfg.codec, 1 if quantized else FEATURE_DTYPES[cfg.dtype].itemsize)
    assert len(mask_raw) == enc.voxel_mask_raw_size
    assert len(values_raw) == enc.values_raw_size
    assert len(conf_raw) == enc.confidence_raw_size
    if cfg.codec == "none":
        assert len(enc.voxel_mask) == enc.voxel_mask_raw_size
        assert len(enc.values) == enc.values_raw_size
        assert len(enc.confidence) == enc.confidence_raw_size

    if enc.sparse:  # numpy packbits, little bit order, flat C order; padding bits clear
        bits = np.unpackbits(np.frombuffer(mask_raw, np.uint8), bitorder="little")
        np.testing.assert_array_equal(bits[:v].astype(bool), mask)
        assert not bits[v:].any()
    carried = features.reshape(channels, -1)[:, mask]
    wire = _wire_values(values_raw, cfg.dtype, channels, n)
    if quantized:
        levels = QUANT_LEVELS[cfg.dtype]
        assert wire.min(initial=0) >= -levels and wire.max(initial=0) <= levels  # symmetric levels
        # value = q * quant_scale[c] + quant_offset[c], the float32 parameters
        # applied in float64 (near float32's limits float32 arithmetic overflows)
        scale = np.asarray(enc.quant_scale, np.float32).astype(np.float64)[:, None]
        offset = np.asarray(enc.quant_offset, np.float32).astype(np.float64)[:, None]
        approx = wire.astype(np.float64) * scale + offset
        target = carried.astype(np.float64)
        if n:
            lo, hi = _quant_range(target, cfg.dtype)
            target = np.clip(target, lo[:, None], hi[:, None])
        err = np.abs(approx - target)
        bound = scale / 2 + 4 * EPS32 * np.abs(carried.astype(np.float64)).max(axis=1, keepdims=True, initial=0) + 1e-37
        assert np.all(err <= bound)
    else:
        np.testing.assert_array_equal(wire, carried.astype(FEATURE_DTYPES[cfg.dtype]))
    if enc.has_confidence:
        carried_conf = confidence.reshape(-1)[mask]
        if quantized:  # uint8 = round(255 * c)
            np.testing.assert_array_equal(np.frombuffer(conf_raw, np.uint8), np.rint(carried_conf * 255))
        else:
            np.testing.assert_array_equal(
                np.frombuffer(conf_raw, FEATURE_DTYPES[cfg.dtype]), carried_conf.astype(FEATURE_DTYPES[cfg.dtype])
            )


def check_feature_round_trip(grid, features, confidence, cfg):
    enc = encode_features(features, confidence, grid, cfg)
    dec = decode_features(enc)
    assert isinstance(dec, DecodedFeatures)
    channels = features.shape[0]
    assert dec.features.dtype == np.float32 and dec.features.shape == (channels, *grid.dims)
    assert dec.mask.dtype == bool and dec.mask.shape == grid.dims
    mask = dec.mask.reshape(-1)

    _check_selection(features, confidence, cfg, mask, enc.num_voxels)
    _check_sizes_and_wire(enc, features, confidence, cfg, mask)

    flat_in = features.reshape(channels, -1)
    flat_out = dec.features.reshape(channels, -1)
    assert np.all(flat_out[:, ~mask] == 0), "voxels not carried must decode to 0"
    _check_values(cfg.dtype, flat_in[:, mask], flat_out[:, mask], enc)

    if confidence is None:
        assert dec.confidence is None
        assert enc.confidence == b"" and enc.confidence_raw_size == 0
    else:  # also when no voxel is carried: then all zero
        assert dec.confidence is not None
        assert dec.confidence.dtype == np.float32 and dec.confidence.shape == grid.dims
        conf_out = dec.confidence.reshape(-1)
        assert np.all(conf_out[~mask] == 0), "voxels not carried must decode to confidence 0"
        _check_confidence(cfg.dtype, confidence.reshape(-1)[mask], conf_out[mask])
    return enc, dec


def _round_trip_test(setting):
    dtype, selection, codec_name, with_conf = setting

    @settings(max_examples=20)
    @given(case=feature_cases(dtype, selection, codec_name, with_conf))
    def run(case):
        grid, features, confidence, cfg = case
        check_feature_round_trip(grid, features, confidence, cfg)

    run()


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no overflow anywhere, encoder or decoder
@pytest.mark.parametrize("setting", ALL_SETTINGS, ids=[_id(s) for s in ALL_SETTINGS])
def test_feature_round_trip(setting):
    _round_trip_test(setting)


def test_all_settings_are_covered():
    # 4 dtypes x 4 selections x 3 codecs x {with, without confidence}, minus threshold without confidence
    # ("request" without a request map ranks as "topk": what a vehicle sends before the first request arrives)
    assert len(ALL_SETTINGS) == 4 * 4 * 3 * 2 - 4 * 3
    assert set(FEATURE_DTYPES) == {"float32", "float16", "int8", "int4"}
    assert set(SELECTIONS) == {"dense", "topk", "threshold", "request"}
    assert set(CODECS) == {"shuffle-zstd", "zstd", "none"}


@pytest.mark.parametrize("codec_name", CODECS)
@settings(max_examples=30)
@given(volume=feature_volumes(with_confidence=False))
def test_float32_dense_is_bit_exact(codec_name, volume):
    grid, features, _ = volume
    dec = decode_features(encode_features(features, None, grid, FeatureCodecConfig(dtype="float32", codec=codec_name)))
    np.testing.assert_array_equal(dec.features.view(np.uint32), features.view(np.uint32))
    assert dec.mask.all()


def test_float32_keeps_signed_zero_and_extremes():
    grid = _grid((2, 2, 2))
    tiny = np.float32(np.finfo(np.float32).smallest_subnormal)
    big = np.finfo(np.float32).max
    f = np.array([0.0, -0.0, tiny, -tiny, big, -big, 1.0, -1.0], np.float32).reshape(1, 2, 2, 2)
    for codec_name in CODECS:
        dec = decode_features(encode_features(f, None, grid, FeatureCodecConfig(dtype="float32", codec=codec_name)))
        np.testing.assert_array_equal(dec.features.view(np.uint32), f.view(np.uint32))


# ---------------------------------------------------------------------------
# selection: deterministic cases


def test_topk_by_confidence_keeps_the_highest():
    grid = _grid((2, 2, 2))
    conf = np.array([0.1, 0.9, 0.3, 0.8, 0.2, 0.7, 0.0, 0.5], np.float32).reshape(grid.dims)
    f = np.arange(8, dtype=np.float32).reshape(1, 2, 2, 2) + 1
    enc = encode_features(f, conf, grid, FeatureCodecConfig(dtype="float32", selection="topk", topk=3))
    dec = decode_features(enc)
    np.testing.assert_array_equal(np.flatnonzero(dec.mask), [1, 3, 5])
    np.testing.assert_array_equal(dec.features.ravel(), [0, 2, 0, 4, 0, 6, 0, 0])
    np.testing.assert_array_equal(dec.confidence.ravel(), np.where(dec.mask.ravel(), conf.ravel(), 0))


def test_topk_without_confidence_ranks_by_l2_norm_over_channels():
    grid = _grid((1, 1, 4))
    # per voxel (c0, c1): norms 5, 1, 13, 2 -> the two largest are voxels 2 and 0;
    # voxel 1 has the largest |c0| but a small norm, voxel 3 the largest single entry of neither
    f = np.array([[3.0, 1.0, 5.0, 0.0], [4.0, 0.0, -12.0, -2.0]], np.float32).reshape(2, 1, 1, 4)
    enc = encode_features(f, None, grid, FeatureCodecConfig(dtype="float32", selection="topk", topk=2))
    np.testing.assert_array_equal(np.flatnonzero(decode_features(enc).mask), [0, 2])


def test_topk_at_least_volume_keeps_every_voxel_sparsely():
    grid = _grid((2, 3, 1))
    f = np.ones((1, 2, 3, 1), np.float32)
    for k in (6, 7, 4096):
        enc = encode_features(f, None, grid, FeatureCodecConfig(dtype="float32", selection="topk", topk=k))
        assert enc.sparse and enc.num_voxels == 6
        assert decode_features(enc).mask.all()


def test_threshold_keeps_ties_and_can_keep_nothing():
    grid = _grid((1, 2, 2))
    conf = np.array([0.25, 0.5, 0.75, 0.5], np.float32).reshape(grid.dims)
    f = np.full((2, 1, 2, 2), 3.0, np.float32)
    enc = encode_features(f, conf, grid, FeatureCodecConfig(dtype="int8", selection="threshold", threshold=0.5))
    np.testing.assert_array_equal(decode_features(enc).mask.ravel(), [False, True, True, True])

    for dtype in FEATURE_DTYPES:
        for codec_name in CODECS:
            cfg = FeatureCodecConfig(dtype=dtype, selection="threshold", threshold=1.0, codec=codec_name)
            enc = encode_features(f, conf, grid, cfg)
            assert enc.sparse and enc.num_voxels == 0
            assert enc.values_raw_size == 0 and enc.confidence_raw_size == 0
            dec = decode_features(enc)
            assert not dec.mask.any()
            assert dec.features.shape == (2, *grid.dims) and np.all(dec.features == 0)


@pytest.mark.parametrize("codec_name", CODECS)
@pytest.mark.parametrize("dtype", list(FEATURE_DTYPES))
def test_empty_selection_keeps_confidence(dtype, codec_name):
    grid = _grid((1, 2, 2))
    conf = np.array([0.25, 0.5, 0.75, 0.5], np.float32).reshape(grid.dims)
    f = np.full((2, 1, 2, 2), 3.0, np.float32)
    cfg = FeatureCodecConfig(dtype=dtype, selection="threshold", threshold=0.9, codec=codec_name)
    enc = encode_features(f, conf, grid, cfg)
    assert enc.num_voxels == 0
    assert enc.has_confidence and enc.confidence == b"" and enc.confidence_raw_size == 0
    dec = decode_features(enc)
    assert dec.confidence is not None, "the sender had a confidence volume; the receiver lost it"
    np.testing.assert_array_equal(dec.confidence, np.zeros(grid.dims, np.float32))


def test_int8_constant_channel_is_exact():
    grid = _grid((2, 2, 2))
    f = np.stack([np.full((2, 2, 2), 7.25, np.float32), np.linspace(-1, 1, 8, dtype=np.float32).reshape(2, 2, 2)])
    enc = encode_features(f, None, grid, FeatureCodecConfig(dtype="int8"))
    assert enc.quant_scale[0] == 0.0
    np.testing.assert_array_equal(decode_features(enc).features[0], f[0])


def test_int4_packs_two_values_a_byte_and_spends_its_levels_on_the_bulk():
    """Half of int8's payload; an outlier saturates instead of coarsening every other value's step."""
    rng = np.random.default_rng(11)
    grid = _grid((8, 8, 5))  # 320 voxels: an odd count of values below (3 rows x 107 voxels)
    f = rng.normal(size=(3, *grid.dims)).astype(np.float32)
    conf = rng.uniform(0, 0.9, size=grid.dims).astype(np.float32)
    f[0, 0, 0, 0], conf[0, 0, 0] = 8.0, 1.0  # an outlier among standard normals, surely sent
    cfg = FeatureCodecConfig("int4", "topk", topk=107, codec="none")
    enc = encode_features(f, conf, grid, cfg)
    int8 = encode_features(f, conf, grid, FeatureCodecConfig("int8", "topk", topk=107, codec="none"))
    assert enc.values_raw_size == len(enc.values) == 161 and int8.values_raw_size == 321
    np.testing.assert_array_equal(enc.voxel_mask, int8.voxel_mask)
    np.testing.assert_array_equal(enc.confidence, int8.confidence)  # uint8 confidence, as int8's
    dec = decode_features(enc)
    mask = dec.mask.reshape(-1)
    assert mask[0]
    sent, got = f.reshape(3, -1)[:, mask].astype(np.float64), dec.features.reshape(3, -1)[:, mask]
    scale = np.asarray(enc.quant_scale, np.float64)
    assert scale[0] < 0.7 * (sent[0].max() - sent[0].min()) / 14  # finer than 15 levels over min..max
    assert got[0, 0] == pytest.approx(enc.quant_offset[0] + 7 * scale[0], rel=1e-6) and got[0, 0] < 5  # saturated
    bulk = np.abs(sent) < 2.5
    assert np.all(np.abs(got - sent)[bulk] <= np.broadcast_to(scale[:, None], sent.shape)[bulk] / 2 + 1e-6)
    assert FeatureCodecConfig("int4", "request", max_bytes=65536, rank=12).name == "int4-request64KB-pca12-zstd"


def test_int8_confidence_levels():
    grid = _grid((1, 1, 5))
    conf = np.array([0.0, 1.0, 0.5, 1 / 255, 254.4 / 255], np.float32).reshape(grid.dims)
    f = np.zeros((1, 1, 1, 5), np.float32)
    enc = encode_features(f, conf, grid, FeatureCodecConfig(dtype="int8", codec="none"))
    np.testing.assert_array_equal(np.frombuffer(enc.confidence, np.uint8), [0, 255, 128, 1, 254])
    dec = decode_features(enc)
    np.testing.assert_allclose(dec.confidence.ravel(), np.array([0, 255, 128, 1, 254]) / 255, rtol=0, atol=1e-7)


def test_zstd_compresses_and_none_does_not():
    grid = _grid((8, 8, 8))
    f = np.zeros((4, 8, 8, 8), np.float32)
    z = encode_features(f, None, grid, FeatureCodecConfig(dtype="float32", codec="zstd"))
    n = encode_features(f, None, grid, FeatureCodecConfig(dtype="float32", codec="none"))
    assert z.raw_bytes == n.raw_bytes == n.payload_bytes == 4 * 512 * 4
    assert z.payload_bytes < z.raw_bytes / 10
    assert zstandard.get_frame_parameters(z.values).content_size == z.values_raw_size


def test_encode_accepts_other_float_inputs():
    grid = _grid((2, 1, 1))
    f64 = np.array([[[[0.1]], [[-2.5]]]], np.float64)
    dec = decode_features(encode_features(f64, None, grid, FeatureCodecConfig(dtype="float32")))
    np.testing.assert_array_equal(dec.features, f64.astype(np.float32))


def test_config_name_and_defaults():
    cfg = FeatureCodecConfig()
    assert (cfg.dtype, cfg.selection, cfg.codec, cfg.zstd_level) == ("float16", "dense", "shuffle-zstd", 1)
    assert cfg.name == "float16-dense-shuffle-zstd"
    assert FeatureCodecConfig(selection="topk").name == "float16-topk4096-shuffle-zstd"
    assert (
        FeatureCodecConfig(dtype="int8", selection="threshold", threshold=0.25, codec="none").name
        == "int8-conf0.25-none"
    )
    assert FeatureCodecConfig(dtype="float32", selection="topk", topk=7, codec="zstd").name == "float32-topk7-zstd"
    # one-byte values are their own shuffle: zstd, at zstd's level
    int8 = FeatureCodecConfig(dtype="int8", selection="topk")
    assert (int8.wire_codec, int8.zstd_level, int8.name) == ("zstd", 3, "int8-topk4096-zstd")
    assert FeatureCodecConfig(codec="zstd", level=0).zstd_level == 3
    assert FeatureCodecConfig(level=5).zstd_level == 5
    assert DEFAULT_MAX_RAW_BYTES == 256 * MIB


def test_encoded_dataclasses_are_frozen():
    grid = _grid((1, 1, 1))
    enc = encode_features(np.zeros((1, 1, 1, 1), np.float32), None, grid, FeatureCodecConfig())
    with pytest.raises(dataclasses.FrozenInstanceError):
        enc.values = b""  # type: ignore[misc]
    lab = encode_labels(np.zeros((1, 1, 1), np.uint8), grid, 24)
    with pytest.raises(dataclasses.FrozenInstanceError):
        lab.labels = b""  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        FeatureCodecConfig().dtype = "int8"  # type: ignore[misc]


# ---------------------------------------------------------------------------
# labels


@st.composite
def label_cases(draw, with_confidence: bool):
    dims = draw(st.tuples(st.integers(1, 8), st.integers(1, 8), st.integers(1, 8)))
    num_classes = draw(st.integers(1, 255))
    values = st.one_of(st.integers(0, num_classes - 1), st.just(255)).map(np.uint8)
    labels = draw(arrays(np.uint8, dims, elements=values))
    confidence = draw(arrays(np.uint8, dims)) if with_confidence else None
    return _grid(dims), num_classes, labels, confidence


@pytest.mark.parametrize("with_conf", [False, True], ids=["noconf", "conf"])
@pytest.mark.parametrize("codec_name", CODECS)
@settings(max_examples=30)
@given(data=st.data())
def test_labels_round_trip_is_lossless(codec_name, with_conf, data):
    grid, num_classes, labels, confidence = data.draw(label_cases(with_conf))
    enc = encode_labels(labels, grid, num_classes, confidence=confidence, codec=codec_name)
    assert enc.codec == codec_name and enc.num_classes == num_classes and enc.grid == grid
    v = grid.num_voxels
    assert enc.labels_raw_size == v
    assert enc.confidence_raw_size == (v if with_conf else 0)
    assert enc.payload_bytes == len(enc.labels) + len(enc.confidence)
    assert enc.raw_bytes == enc.labels_raw_size + enc.confidence_raw_size
    # wire layout: uint8[nx*ny*nz] in flat C order
    assert _raw_field(enc.labels, codec_name) == labels.tobytes(order="C")
    if codec_name == "none":
        assert len(enc.labels) == v and len(enc.confidence) == enc.confidence_raw_size

    dec = decode_labels(enc)
    assert isinstance(dec, DecodedLabels)
    assert dec.labels.dtype == np.uint8 and dec.labels.shape == grid.dims
    np.testing.assert_array_equal(dec.labels, labels)
    if with_conf:
        assert _raw_field(enc.confidence, codec_name) == confidence.tobytes(order="C")
        assert dec.confidence.dtype == np.uint8
        np.testing.assert_array_equal(dec.confidence, confidence)
    else:
        assert dec.confidence is None and enc.confidence == b""


def test_labels_ignore_value_and_top_class():
    grid = _grid((1, 1, 4))
    labels = np.array([0, 23, 255, 7], np.uint8).reshape(grid.dims)
    np.testing.assert_array_equal(decode_labels(encode_labels(labels, grid, 24)).labels, labels)
    one = np.array([0, 255, 0, 0], np.uint8).reshape(grid.dims)
    np.testing.assert_array_equal(decode_labels(encode_labels(one, grid, 1)).labels, one)


# ---------------------------------------------------------------------------
# errors: one test per error, each names its field


@pytest.fixture(scope="module")
def small():
    """Encoded sparse int8 features with confidence (every payload field non-empty) and labels."""
    grid = _grid((3, 4, 5))
    rng = np.random.default_rng(7)
    features = rng.standard_normal((3, *grid.dims)).astype(np.float32)
    confidence = rng.uniform(0, 1, grid.dims).astype(np.float32)
    feats = encode_features(features, confidence, grid, FeatureCodecConfig(dtype="int8", selection="topk", topk=20))
    labels = encode_labels(
        rng.integers(0, 24, grid.dims, dtype=np.uint8),
        grid,
        24,
        confidence=rng.integers(0, 256, grid.dims, dtype=np.uint8),
    )
    return grid, features, confidence, feats, labels


FEATURE_FIELDS = {"voxel_mask": "voxel_mask", "values": "values", "confidence": "confidence"}
LABEL_FIELDS = {"labels": "labels", "confidence": "confidence"}


def test_every_error_is_a_co3sop_error():
    for exc in (CodecError, UnknownCodecError, CorruptPayloadError, SizeMismatchError, PayloadTooLargeError):
        assert issubclass(exc, Co3sopError)
        assert issubclass(exc, CodecError)
    assert issubclass(Co3sopError, Exception)


@pytest.mark.parametrize("field", FEATURE_FIELDS)
@settings(max_examples=15)
@given(data=st.data())
def test_truncated_feature_payload(small, field, data):
    enc = small[3]
    payload = getattr(enc, field)
    cut = data.draw(st.integers(0, len(payload) - 1), label="cut")
    with pytest.raises(CorruptPayloadError) as info:
        decode_features(dataclasses.replace(enc, **{field: payload[:cut]}))
    _assert_error(info, CorruptPayloadError, field)


@pytest.mark.parametrize("field", LABEL_FIELDS)
@settings(max_examples=15)
@given(data=st.data())
def test_truncated_label_payload(small, field, data):
    enc = small[4]
    payload = getattr(enc, field)
    cut = data.draw(st.integers(0, len(payload) - 1), label="cut")
    with pytest.raises(CorruptPayloadError) as info:
        decode_labels(dataclasses.replace(enc, **{field: payload[:cut]}))
    _assert_error(info, CorruptPayloadError, field)


def test_labels_alone_leave_the_confidence_undecoded(small):
    """Readers of the labels alone skip the confidence: the same labels, and a damaged confidence goes unread."""
    enc = small[4]
    whole, alone = decode_labels(enc), decode_labels(enc, with_confidence=False)
    np.testing.assert_array_equal(alone.labels, whole.labels)
    assert alone.confidence is None and whole.confidence is not None
    damaged = dataclasses.replace(enc, confidence=enc.confidence[:3])
    np.testing.assert_array_equal(decode_labels(damaged, with_confidence=False).labels, whole.labels)
    with pytest.raises(CorruptPayloadError):
        decode_labels(damaged)
    with pytest.raises(CorruptPayloadError):  # the labels themselves are still checked
        decode_labels(dataclasses.replace(enc, labels=enc.labels[:3]), with_confidence=False)


@pytest.mark.parametrize("index", range(5))  # the 4 magic bytes and the frame header descriptor
@pytest.mark.parametrize("field", FEATURE_FIELDS)
def test_corrupt_feature_payload(small, field, index):
    enc = small[3]
    bad = bytearray(getattr(enc, field))
    bad[index] ^= 0xFF
    with pytest.raises(CorruptPayloadError) as info:
        decode_features(dataclasses.replace(enc, **{field: bytes(bad)}))
    _assert_error(info, CorruptPayloadError, field)


@pytest.mark.parametrize("field", LABEL_FIELDS)
def test_corrupt_label_payload(small, field):
    enc = small[4]
    bad = bytearray(getattr(enc, field))
    bad[0:4] = b"\x00\x00\x00\x00"  # not a zstd frame at all
    with pytest.raises(CorruptPayloadError) as info:
        decode_labels(dataclasses.replace(enc, **{field: bytes(bad)}))
    _assert_error(info, CorruptPayloadError, field)


def test_non_zstd_bytes_are_corrupt(small):
    enc = small[3]
    with pytest.raises(CorruptPayloadError) as info:
        decode_features(dataclasses.replace(enc, values=b"\x01" * len(enc.values)))
    _assert_error(info, CorruptPayloadError, "values")


def test_flipped_byte_in_block_body_is_detected():
    grid = _grid((4, 4, 4))
    features = np.random.default_rng(0).standard_normal((3, *grid.dims)).astype(np.float32)
    enc = encode_features(features, None, grid, FeatureCodecConfig(dtype="float32", codec="zstd"))
    bad = bytearray(enc.values)
    bad[len(bad) // 2] ^= 0x01  # one bit, well past the frame header
    with pytest.raises(CorruptPayloadError) as info:
        decode_features(dataclasses.replace(enc, values=bytes(bad)))
    _assert_error(info, CorruptPayloadError, "values")


def test_trailing_bytes_after_frame_are_corrupt(small):
    enc = small[4]
    with pytest.raises(CorruptPayloadError) as info:
        decode_labels(dataclasses.replace(enc, labels=enc.labels + b"trailing junk"))
    _assert_error(info, CorruptPayloadError, "labels")
    # a second, valid frame after the first is trailing data too
    feats = small[3]
    with pytest.raises(CorruptPayloadError) as info:
        decode_features(dataclasses.replace(feats, values=feats.values + feats.values))
    _assert_error(info, CorruptPayloadError, "values")


def _frame(raw: bytes, *, checksum: bool = True, content_size: bool = True) -> bytes:
    return zstandard.ZstdCompressor(level=3, write_checksum=checksum, write_content_size=content_size).compress(raw)


def _assert_frame_lacks(frame: bytes, missing: str) -> None:
    """The forged frame really lacks `missing` and has the other field."""
    params = zstandard.get_frame_parameters(frame)
    assert params.has_checksum is (missing != "checksum")
    assert (params.content_size == zstandard.CONTENTSIZE_UNKNOWN) is (missing == "content_size")


def test_encoder_writes_checksum_and_content_size(small):
    for enc, fields in ((small[3], FEATURE_FIELDS), (small[4], LABEL_FIELDS)):
        for field in fields:
            params = zstandard.get_frame_parameters(getattr(enc, field))
            assert params.has_checksum, field
            assert params.content_size == getattr(enc, f"{field}_raw_size"), field


@pytest.mark.parametrize("missing", ["checksum", "content_size"])
@pytest.mark.parametrize("field", FEATURE_FIELDS)
def test_feature_frame_without_checksum_or_content_size_is_corrupt(small, field, missing):
    enc = small[3]
    raw = zstandard.ZstdDecompressor().decompress(getattr(enc, field))
    # control: the same bytes in a complete frame decode
    decode_features(dataclasses.replace(enc, **{field: _frame(raw)}))
    forged = _frame(raw, **{missing: False})
    _assert_frame_lacks(forged, missing)
    with pytest.raises(CorruptPayloadError) as info:
        decode_features(dataclasses.replace(enc, **{field: forged}))
    _assert_error(info, CorruptPayloadError, field)


@pytest.mark.parametrize("missing", ["checksum", "content_size"])
@pytest.mark.parametrize("field", LABEL_FIELDS)
def test_label_frame_without_checksum_or_content_size_is_corrupt(small, field, missing):
    enc = small[4]
    raw = zstandard.ZstdDecompressor().decompress(getattr(enc, field))
    decode_labels(dataclasses.replace(enc, **{field: _frame(raw)}))
    forged = _frame(raw, **{missing: False})
    _assert_frame_lacks(forged, missing)
    with pytest.raises(CorruptPayloadError) as info:
        decode_labels(dataclasses.replace(enc, **{field: forged}))
    _assert_error(info, CorruptPayloadError, field)


@pytest.mark.parametrize("codec_name", CODECS)
def test_confidence_payload_without_has_confidence(small, codec_name):
    """A confidence payload the sender says it does not carry is a size mismatch, not silently used or dropped."""
    grid, features, confidence, _, _ = small
    cfg = FeatureCodecConfig(dtype="float16", selection="topk", topk=20, codec=codec_name)
    enc = encode_features(features, confidence, grid, cfg)
    assert enc.has_confidence and enc.confidence and enc.confidence_raw_size
    for forged in (
        {"has_confidence": False},  # payload and size
        {"has_confidence": False, "confidence_raw_size": 0},  # payload only
        {"has_confidence": False, "confidence": b""},  # size only
    ):
        with pytest.raises(SizeMismatchError) as info:
            decode_features(dataclasses.replace(enc, **forged))
        _assert_error(info, SizeMismatchError, "confidence")
    # all three cleared: decodes without confidence, features unchanged
    dec = decode_features(dataclasses.replace(enc, has_confidence=False, confidence=b"", confidence_raw_size=0))
    assert dec.confidence is None
    np.testing.assert_array_equal(dec.features, decode_features(enc).features)


def _forge(enc: EncodedFeatures, field: str, fill) -> EncodedFeatures:
    """`enc` with the decompressed array of `field` rewritten by `fill` (what a faulty sender would encode)."""
    dtype = FEATURE_DTYPES[enc.dtype]
    if field in ("quant_scale", "quant_offset"):
        return dataclasses.replace(enc, **{field: tuple(fill(np.asarray(getattr(enc, field), np.float32)))})
    cdtype = codec._confidence_dtype(enc.dtype) if field == "confidence" else dtype
    raw = _raw_field(getattr(enc, field), enc.codec, cdtype.itemsize)
    forged = fill(np.frombuffer(raw, cdtype).copy()).tobytes()
    if enc.codec == "shuffle-zstd":  # as it was sent: byte k of every element as plane k
        forged = np.frombuffer(forged, np.uint8).reshape(-1, cdtype.itemsize).T.tobytes()
    payload = zstandard.ZstdCompressor(write_checksum=True, write_content_size=True).compress(forged)
    return dataclasses.replace(enc, **{field: payload})


def _poison(a: np.ndarray, value: float) -> np.ndarray:
    a[len(a) // 2] = value
    return a


NON_FINITE_CASES = [
    ("values", "float32"),
    ("values", "float16"),
    ("confidence", "float32"),
    ("confidence", "float16"),
    ("quant_scale", "int8"),
    ("quant_offset", "int8"),
]


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize("field,dtype", NON_FINITE_CASES, ids=[f"{f}-{d}" for f, d in NON_FINITE_CASES])
def test_non_finite_payloads_are_refused(small, field, dtype, value):
    """A sender's NaN or inf in any field would spread through fusion to the whole map: the message is refused."""
    grid, features, confidence, _, _ = small
    enc = encode_features(features, confidence, grid, FeatureCodecConfig(dtype=dtype))
    with pytest.raises(NonFiniteError) as info:
        decode_features(_forge(enc, field, lambda a: _poison(a, value)))
    _assert_error(info, NonFiniteError, field, "NaN or infinite")


@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_float_confidence_outside_unit_interval_is_refused(small, dtype):
    grid, features, confidence, _, _ = small
    enc = encode_features(features, confidence, grid, FeatureCodecConfig(dtype=dtype))
    with pytest.raises(CodecError) as info:
        decode_features(_forge(enc, "confidence", lambda a: _poison(a, 1.5)))
    _assert_error(info, CodecError, "confidence", "[0, 1]")


@pytest.mark.parametrize("codec_name", CODECS)
def test_has_confidence_without_payload(small, codec_name):
    grid, features, _, _, _ = small
    enc = encode_features(
        features, None, grid, FeatureCodecConfig(dtype="float32", selection="topk", topk=20, codec=codec_name)
    )
    assert not enc.has_confidence
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, has_confidence=True))
    _assert_error(info, SizeMismatchError, "confidence")


@pytest.mark.parametrize(
    "field,raw_field",
    [("voxel_mask", "voxel_mask_raw_size"), ("values", "values_raw_size"), ("confidence", "confidence_raw_size")],
)
@pytest.mark.parametrize("delta", [-1, 1])
def test_declared_feature_size_differs_from_grid(small, field, raw_field, delta):
    enc = small[3]
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, **{raw_field: getattr(enc, raw_field) + delta}))
    _assert_error(info, SizeMismatchError, field, "declares")


def test_grid_differs_from_payload(small):
    grid, _, _, enc, lab = small
    other = GridSpec(grid.origin, grid.voxel_size, (grid.dims[0] + 8, *grid.dims[1:]))
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, grid=other))
    _assert_error(info, SizeMismatchError, "voxel_mask")
    with pytest.raises(SizeMismatchError) as info:
        decode_labels(dataclasses.replace(lab, grid=other))
    _assert_error(info, SizeMismatchError, "labels")


def test_channels_differ_from_payload(small):
    enc = small[3]
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, channels=enc.channels + 1, quant_scale=enc.quant_scale + (1.0,)))
    _assert_error(info, SizeMismatchError, "values")
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, channels=0))
    _assert_error(info, SizeMismatchError, "channels")


@pytest.mark.parametrize("raw_field,field", [("labels_raw_size", "labels"), ("confidence_raw_size", "confidence")])
def test_declared_label_size_differs_from_grid(small, raw_field, field):
    enc = small[4]
    with pytest.raises(SizeMismatchError) as info:
        decode_labels(dataclasses.replace(enc, **{raw_field: getattr(enc, raw_field) - 1}))
    _assert_error(info, SizeMismatchError, field)


def test_uncompressed_payload_of_wrong_length(small):
    grid, features, confidence, _, _ = small
    enc = encode_features(features, confidence, grid, FeatureCodecConfig(dtype="float16", codec="none"))
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, values=enc.values[:-2]))
    _assert_error(info, SizeMismatchError, "values", "carries")
    lab = encode_labels(np.zeros(grid.dims, np.uint8), grid, 24, codec="none")
    with pytest.raises(SizeMismatchError) as info:
        decode_labels(dataclasses.replace(lab, labels=lab.labels + b"\x00"))
    _assert_error(info, SizeMismatchError, "labels", "carries")


@pytest.fixture(scope="module")
def zero_bomb():
    """100 MiB of zeros as one well-formed zstd frame (checksum, content size) of a few KiB."""
    bomb = _frame(bytes(100 * MIB))
    assert len(bomb) < 64 * 1024
    params = zstandard.get_frame_parameters(bomb)
    assert params.has_checksum and params.content_size == 100 * MIB
    return bomb


@pytest.fixture()
def no_decompression(monkeypatch):
    """Fails the test if anything constructs a zstd decompressor."""

    class Forbidden:
        def __init__(self, *args, **kwargs):
            raise AssertionError("decompressed before checking the declared size against the limit")

    monkeypatch.setattr(codec.zstandard, "ZstdDecompressor", Forbidden)


def _peak_bytes(fn):
    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


def test_payload_too_large_features_before_decompressing(zero_bomb, no_decompression):
    grid = _grid((256, 256, 400))  # one float32 channel: exactly 100 MiB dense
    enc = EncodedFeatures(
        grid=grid, channels=1, dtype="float32", codec="zstd", quant_scale=(), quant_offset=(), sparse=False,
        num_voxels=grid.num_voxels, has_confidence=False, voxel_mask=b"", values=zero_bomb, confidence=b"",
        voxel_mask_raw_size=0, values_raw_size=100 * MIB, confidence_raw_size=0,
    )  # fmt: skip
    info = None

    def decode():
        nonlocal info
        with pytest.raises(PayloadTooLargeError) as info:
            decode_features(enc, max_raw_bytes=MIB)

    assert _peak_bytes(decode) < MIB
    _assert_error(info, PayloadTooLargeError, "values", str(100 * MIB), str(MIB))


def test_payload_too_large_labels_before_decompressing(zero_bomb, no_decompression):
    grid = _grid((512, 512, 400))  # uint8 labels: exactly 100 MiB
    enc = EncodedLabels(
        grid=grid,
        num_classes=24,
        codec="zstd",
        labels=zero_bomb,
        labels_raw_size=100 * MIB,
        confidence=b"",
        confidence_raw_size=0,
    )
    info = None

    def decode():
        nonlocal info
        with pytest.raises(PayloadTooLargeError) as info:
            decode_labels(enc, max_raw_bytes=MIB)

    assert _peak_bytes(decode) < MIB
    _assert_error(info, PayloadTooLargeError, "labels", str(MIB))


def test_payload_too_large_even_if_grid_disagrees(small, no_decompression):
    enc = small[3]
    with pytest.raises(PayloadTooLargeError) as info:
        decode_features(dataclasses.replace(enc, voxel_mask_raw_size=1 << 40), max_raw_bytes=MIB)
    _assert_error(info, PayloadTooLargeError, "voxel_mask")
    # (uncompressed, so the values field ahead of it needs no decompressor)
    dense = encode_features(small[1], small[2], small[0], FeatureCodecConfig(dtype="float16", codec="none"))
    with pytest.raises(PayloadTooLargeError) as info:
        decode_features(dataclasses.replace(dense, confidence_raw_size=1 << 40), max_raw_bytes=MIB)
    _assert_error(info, PayloadTooLargeError, "confidence")


def test_limit_is_inclusive_and_configurable():
    grid = _grid((4, 4, 4))
    f = np.ones((2, 4, 4, 4), np.float32)
    enc = encode_features(f, None, grid, FeatureCodecConfig(dtype="float32"))
    assert enc.values_raw_size == 512
    np.testing.assert_array_equal(decode_features(enc, max_raw_bytes=512).features, f)
    with pytest.raises(PayloadTooLargeError) as info:
        decode_features(enc, max_raw_bytes=511)
    _assert_error(info, PayloadTooLargeError, "values", "511")
    lab = encode_labels(np.zeros(grid.dims, np.uint8), grid, 24)
    decode_labels(lab, max_raw_bytes=64)
    with pytest.raises(PayloadTooLargeError) as info:
        decode_labels(lab, max_raw_bytes=63)
    _assert_error(info, PayloadTooLargeError, "labels", "63")


def test_frame_header_cannot_bypass_the_limit(zero_bomb):
    grid = _grid((4, 4, 4))
    enc = EncodedLabels(
        grid=grid,
        num_classes=24,
        codec="zstd",
        labels=zero_bomb,
        labels_raw_size=64,
        confidence=b"",
        confidence_raw_size=0,
    )
    info = None

    def decode():
        nonlocal info
        with pytest.raises(CorruptPayloadError) as info:
            decode_labels(enc, max_raw_bytes=MIB)

    peak = _peak_bytes(decode)
    _assert_error(info, CorruptPayloadError, "labels", str(100 * MIB))  # names the frame's claim
    assert peak < MIB, f"decoding a 64-byte grid under a 1 MiB limit allocated {peak / MIB:.0f} MiB"


def test_unknown_codec(small):
    grid, _, _, enc, lab = small
    with pytest.raises(UnknownCodecError) as info:
        decode_features(dataclasses.replace(enc, codec="lz4"))
    _assert_error(info, UnknownCodecError, "codec", "'lz4'")
    with pytest.raises(UnknownCodecError) as info:
        decode_labels(dataclasses.replace(lab, codec="gzip"))
    _assert_error(info, UnknownCodecError, "codec", "'gzip'")
    with pytest.raises(UnknownCodecError) as info:
        encode_labels(np.zeros(grid.dims, np.uint8), grid, 24, codec="ZSTD")
    _assert_error(info, UnknownCodecError, "codec", "'ZSTD'")
    with pytest.raises(UnknownCodecError) as info:
        FeatureCodecConfig(codec="brotli")
    _assert_error(info, UnknownCodecError, "codec", "'brotli'")


def test_unknown_dtype(small):
    enc = small[3]
    with pytest.raises(UnknownCodecError) as info:
        decode_features(dataclasses.replace(enc, dtype="bfloat16"))
    _assert_error(info, UnknownCodecError, "dtype", "'bfloat16'")
    with pytest.raises(UnknownCodecError) as info:
        FeatureCodecConfig(dtype="float64")
    _assert_error(info, UnknownCodecError, "dtype", "'float64'")


def test_unknown_selection():
    with pytest.raises(UnknownCodecError) as info:
        FeatureCodecConfig(selection="random")
    _assert_error(info, UnknownCodecError, "selection", "'random'")


@pytest.mark.parametrize("topk", [0, -1, 2.5, 4096.0, "5", None], ids=repr)
def test_bad_topk(topk):
    with pytest.raises(CodecError) as info:
        FeatureCodecConfig(selection="topk", topk=topk)
    _assert_error(info, CodecError, "topk")


@pytest.mark.parametrize("threshold", [1.5, -0.1, 1.0000001, np.nan, np.inf, -np.inf], ids=repr)
def test_bad_threshold(threshold):
    with pytest.raises(CodecError) as info:
        FeatureCodecConfig(selection="threshold", threshold=threshold)
    _assert_error(info, CodecError, "threshold")


def test_config_limits_are_inclusive():
    assert FeatureCodecConfig(selection="topk", topk=1).topk == 1
    assert FeatureCodecConfig(selection="threshold", threshold=0.0).threshold == 0.0
    assert FeatureCodecConfig(selection="threshold", threshold=1.0).threshold == 1.0
    assert FeatureCodecConfig(selection="threshold", threshold=np.float32(0.5)).threshold == 0.5


@pytest.mark.parametrize("delta", [-1, 1])
def test_num_voxels_differs_from_mask(small, delta):
    enc = small[3]
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, num_voxels=enc.num_voxels + delta))
    _assert_error(info, SizeMismatchError, "num_voxels", "voxel_mask")


def test_num_voxels_differs_from_dense_grid():
    grid = _grid((2, 2, 2))
    enc = encode_features(np.zeros((1, 2, 2, 2), np.float32), None, grid, FeatureCodecConfig(dtype="float32"))
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, num_voxels=7))
    _assert_error(info, SizeMismatchError, "num_voxels")


@pytest.mark.parametrize("which", ["quant_scale", "quant_offset"])
@pytest.mark.parametrize("change", ["short", "long", "empty"])
def test_quant_params_of_wrong_length(small, which, change):
    enc = small[3]
    value = getattr(enc, which)
    forged = {"short": value[:-1], "long": value + (1.0,), "empty": ()}[change]
    with pytest.raises(SizeMismatchError) as info:
        decode_features(dataclasses.replace(enc, **{which: forged}))
    _assert_error(info, SizeMismatchError, "quant_scale")


def test_unknown_label_value_on_encode():
    grid = _grid((1, 1, 3))
    with pytest.raises(CodecError) as info:
        encode_labels(np.array([0, 24, 3], np.uint8).reshape(grid.dims), grid, 24)
    _assert_error(info, CodecError, "labels", "[24]")
    with pytest.raises(CodecError) as info:
        encode_labels(np.array([0, 254, 3], np.uint8).reshape(grid.dims), grid, 24)
    _assert_error(info, CodecError, "labels", "254")


def test_unknown_label_value_on_decode():
    grid = _grid((1, 1, 3))
    for codec_name in CODECS:
        enc = encode_labels(np.array([0, 5, 3], np.uint8).reshape(grid.dims), grid, 24, codec=codec_name)
        raw = bytes([0, 200, 3])
        # a well-formed frame (checksum, content size), so decoding reaches the label check
        forged = raw if codec_name == "none" else _frame(raw)
        with pytest.raises(CodecError) as info:
            decode_labels(dataclasses.replace(enc, labels=forged))
        _assert_error(info, CodecError, "labels", "200")
        # a class count the labels exceed
        with pytest.raises(CodecError) as info:
            decode_labels(dataclasses.replace(enc, num_classes=5))
        _assert_error(info, CodecError, "labels", "[5]")


@pytest.mark.parametrize("num_classes", [0, 256, -1])
def test_num_classes_out_of_range(num_classes):
    grid = _grid((1, 1, 1))
    with pytest.raises(CodecError) as info:
        encode_labels(np.zeros(grid.dims, np.uint8), grid, num_classes)
    _assert_error(info, CodecError, "num_classes")
    enc = encode_labels(np.zeros(grid.dims, np.uint8), grid, 24)
    with pytest.raises(CodecError) as info:
        decode_labels(dataclasses.replace(enc, num_classes=num_classes))
    _assert_error(info, CodecError, "num_classes")


def test_labels_of_wrong_dtype_or_shape():
    grid = _grid((2, 2, 2))
    with pytest.raises(CodecError) as info:
        encode_labels(np.zeros(grid.dims, np.int64), grid, 24)
    _assert_error(info, CodecError, "labels", "uint8")
    with pytest.raises(SizeMismatchError) as info:
        encode_labels(np.zeros((2, 2, 3), np.uint8), grid, 24)
    _assert_error(info, SizeMismatchError, "labels")
    with pytest.raises(SizeMismatchError) as info:
        encode_labels(np.zeros(grid.dims, np.uint8), grid, 24, confidence=np.zeros(grid.dims, np.float32))
    _assert_error(info, SizeMismatchError, "confidence")
    with pytest.raises(SizeMismatchError) as info:
        encode_labels(np.zeros(grid.dims, np.uint8), grid, 24, confidence=np.zeros((8,), np.uint8))
    _assert_error(info, SizeMismatchError, "confidence")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("dtype", list(FEATURE_DTYPES))
def test_non_finite_features(bad, dtype):
    grid = _grid((2, 2, 2))
    f = np.zeros((2, 2, 2, 2), np.float32)
    f[1, 1, 0, 1] = bad
    with pytest.raises(CodecError) as info:
        encode_features(f, None, grid, FeatureCodecConfig(dtype=dtype))
    _assert_error(info, CodecError, "features")


@pytest.mark.parametrize("bad", [np.nan, -0.01, 1.01, np.inf])
def test_confidence_out_of_range(bad):
    grid = _grid((2, 2, 2))
    conf = np.full(grid.dims, 0.5, np.float32)
    conf[0, 1, 1] = bad
    with pytest.raises(CodecError) as info:
        encode_features(np.zeros((1, 2, 2, 2), np.float32), conf, grid, FeatureCodecConfig())
    _assert_error(info, CodecError, "confidence")


def test_threshold_selection_needs_confidence():
    grid = _grid((2, 2, 2))
    with pytest.raises(CodecError) as info:
        encode_features(np.ones((1, 2, 2, 2), np.float32), None, grid, FeatureCodecConfig(selection="threshold"))
    _assert_error(info, CodecError, "threshold", "confidence")


@pytest.mark.parametrize("shape", [(2, 2, 2), (1, 2, 2, 3), (1, 3, 2, 2), (1, 1, 2, 2, 2)], ids=str)
def test_wrong_feature_shape(shape):
    grid = _grid((2, 2, 2))
    with pytest.raises(SizeMismatchError) as info:
        encode_features(np.zeros(shape, np.float32), None, grid, FeatureCodecConfig())
    _assert_error(info, SizeMismatchError, "features", str(shape))


@pytest.mark.parametrize("selection", SELECTIONS)
def test_zero_feature_channels(selection):
    grid = _grid((2, 2, 2))
    conf = np.full(grid.dims, 0.5, np.float32)
    with pytest.raises(SizeMismatchError) as info:
        encode_features(np.zeros((0, 2, 2, 2), np.float32), conf, grid, FeatureCodecConfig(selection=selection))
    _assert_error(info, SizeMismatchError, "features")


def test_wrong_confidence_shape():
    grid = _grid((2, 2, 2))
    with pytest.raises(SizeMismatchError) as info:
        encode_features(np.zeros((1, 2, 2, 2), np.float32), np.zeros((2, 2), np.float32), grid, FeatureCodecConfig())
    _assert_error(info, SizeMismatchError, "confidence")


@pytest.mark.parametrize("lo_hi", [(-1, 1), (1, 1), (0.5, 1)], ids=["symmetric", "constant", "upper"])
def test_int8_near_float32_limits_stays_finite(lo_hi):
    grid = _grid((2, 1, 1))
    big = np.finfo(np.float32).max
    f = (np.array(lo_hi, np.float64) * big).astype(np.float32).reshape(1, 2, 1, 1)
    enc = encode_features(f, None, grid, FeatureCodecConfig(dtype="int8"))
    with np.errstate(all="raise"):
        dec = decode_features(enc)
    assert np.isfinite(dec.features).all()
    assert np.all(np.abs(dec.features.astype(np.float64) - f) <= enc.quant_scale[0] / 2 * (1 + 1e-6))


@pytest.mark.parametrize("codec_name", CODECS)
@pytest.mark.parametrize("sign", [1, -1])
def test_float16_out_of_range_is_an_error(codec_name, sign):
    grid = _grid((1, 1, 3))
    # 65519.996 still rounds to float16's 65504; 65520 rounds to inf
    ok = np.array([0.0, 1.0, sign * np.nextafter(np.float32(65520), np.float32(0))], np.float32).reshape(1, *grid.dims)
    dec = decode_features(encode_features(ok, None, grid, FeatureCodecConfig(dtype="float16", codec=codec_name)))
    np.testing.assert_array_equal(dec.features.ravel(), [0.0, 1.0, sign * F16_MAX])
    for big in (65520.0, 1e6, float(np.finfo(np.float32).max)):
        f = np.array([0.0, 1.0, sign * big], np.float32).reshape(1, *grid.dims)
        with pytest.raises(CodecError) as info:
            encode_features(f, None, grid, FeatureCodecConfig(dtype="float16", codec=codec_name))
        _assert_error(info, CodecError, "features")
        # float32 and int8 carry the same volume
        for dtype in ("float32", "int8"):
            out = decode_features(
                encode_features(f, None, grid, FeatureCodecConfig(dtype=dtype, codec=codec_name))
            ).features
            assert np.isfinite(out).all()


@pytest.mark.parametrize("order", [(1e20, 3e20), (3e20, 1e20)], ids=["ascending", "descending"])
@pytest.mark.parametrize("channels", [1, 3])
def test_topk_by_norm_with_huge_values(order, channels):
    """Squares of 1e20 overflow float32: the ranking must still tell 1e20 from 3e20."""
    grid = _grid((1, 1, 2))
    f = np.broadcast_to(np.array(order, np.float32), (channels, 2)).reshape(channels, *grid.dims).copy()
    enc = encode_features(f, None, grid, FeatureCodecConfig(dtype="float32", selection="topk", topk=1))
    dec = decode_features(enc)
    larger = int(np.argmax(order))
    np.testing.assert_array_equal(np.flatnonzero(dec.mask), [larger])
    np.testing.assert_array_equal(dec.features[:, 0, 0, larger], np.float32(3e20))


def test_encoded_features_mirror_voxel_features_msg():
    """EncodedFeatures has exactly the codec fields of VoxelFeatures.msg (has_confidence included)."""
    msg_fields = {}
    for line in (MSG_DIR / "VoxelFeatures.msg").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            ftype, name = line.split()[:2]
            msg_fields[name] = ftype
    assert VOXEL_FEATURES_ENVELOPE <= set(msg_fields)
    codec_fields = {n: t for n, t in msg_fields.items() if n not in VOXEL_FEATURES_ENVELOPE}
    assert {f.name for f in dataclasses.fields(EncodedFeatures)} == set(codec_fields)
    assert codec_fields["has_confidence"] == "bool" and codec_fields["sparse"] == "bool"
    for name in ("voxel_mask", "values", "confidence"):
        assert codec_fields[name] == "uint8[]"
        assert codec_fields[f"{name}_raw_size"] == "uint64"
    # has_confidence sits with the payload it describes
    order = list(codec_fields)
    assert order.index("values") < order.index("has_confidence") < order.index("confidence")


def test_crafted_frame_header_is_corrupt():
    """A 16-byte frame whose header claims 64 MiB, sent for a 64-voxel grid, is rejected as corrupt."""
    grid = _grid((4, 4, 4))
    frame = struct.pack("<IB", 0xFD2FB528, 0xE0) + struct.pack("<Q", 64 * MIB) + bytes([1, 0, 0])
    enc = encode_labels(np.zeros(grid.dims, np.uint8), grid, 24)
    with pytest.raises(CorruptPayloadError) as info:
        decode_labels(dataclasses.replace(enc, labels=frame), max_raw_bytes=MIB)
    _assert_error(info, CorruptPayloadError, "labels")


def test_codec_config_types():
    assert FeatureCodecConfig(selection="topk", topk=np.int64(5)).topk == 5  # numpy integers are whole numbers
    for bad in (dict(topk=True), dict(threshold="0.5"), dict(threshold=None)):
        with pytest.raises(CodecError):
            FeatureCodecConfig(**bad)


# --- byte budgets and request maps --------------------------------------------------------------------------


def _volume(seed: int = 0, dims=(16, 16, 6), channels: int = 32):
    rng = np.random.default_rng(seed)
    return (
        _grid(dims),
        rng.normal(size=(channels, *dims)).astype(np.float32),
        rng.uniform(size=dims).astype(np.float32),
    )


@pytest.mark.parametrize("selection", ["topk", "request"])
@pytest.mark.parametrize("budget", [2000, 8000, 30000])
def test_budget_keeps_the_most_best_scored_voxels_that_fit(selection, budget):
    grid, features, confidence = _volume()
    request = np.random.default_rng(1).uniform(size=grid.dims).astype(np.float32)
    cfg = FeatureCodecConfig("int8", selection, max_bytes=budget)
    enc = encode_features(features, confidence, grid, cfg, request)
    assert enc.budget_bytes <= budget
    assert enc.budget_bytes == enc.payload_bytes + 4 * 2 * 32  # int8 scale and offset per channel
    # nearly all of the budget is used: one more voxel of 33 raw bytes would not fit much better
    assert enc.budget_bytes > budget - 3 * 33
    mask = decode_features(enc).confidence.reshape(-1) > 0
    score = confidence.reshape(-1) * (request.reshape(-1) if selection == "request" else 1)
    assert score[mask].min() >= score[~mask].max()


@pytest.mark.parametrize("dtype, rank", [("int8", 0), ("int4", 8)])
def test_a_budget_every_requested_voxel_fits_sends_them_all_in_few_encodings(dtype, rank, monkeypatch):
    grid, features, confidence = _volume(3)
    request = np.zeros(grid.dims, np.float32)
    request[:5] = 0.5  # 480 voxels asked for
    unbounded = encode_features(
        features, confidence, grid, FeatureCodecConfig(dtype, "request", max_bytes=2**31 - 1, rank=rank), request
    )
    assert unbounded.num_voxels == 480
    calls, original = [], codec._encode
    monkeypatch.setattr(codec, "_encode", lambda *a: calls.append(1) or original(*a))
    fits = encode_features(
        features,
        confidence,
        grid,
        FeatureCodecConfig(dtype, "request", max_bytes=unbounded.budget_bytes, rank=rank),
        request,
    )
    assert fits == unbounded and len(calls) == 2  # none, then all: no search down to the last voxel
    # a byte less: a search on the count, the best-scored 479 or fewer, in a few tries
    calls.clear()
    tight = encode_features(
        features,
        confidence,
        grid,
        FeatureCodecConfig(dtype, "request", max_bytes=unbounded.budget_bytes - 1, rank=rank),
        request,
    )
    assert tight.num_voxels < 480 and tight.budget_bytes < unbounded.budget_bytes and len(calls) <= 6


@pytest.mark.parametrize("dtype, rank, fill", [("int8", 0, False), ("int4", 8, True)])
@pytest.mark.parametrize("budget", [1500, 6000, 20000])
def test_a_budget_is_searched_to_a_count_that_fits_where_a_few_more_do_not(dtype, rank, fill, budget, monkeypatch):
    """Against every count tried in turn: the count found fits, the largest that fits is at most 0.4 % (or a voxel)
    above it, and it takes far fewer encodings than the bisection's log2 of the candidates."""
    grid, features, confidence = _volume(5, dims=(24, 24, 6))
    request = np.random.default_rng(6).uniform(size=grid.dims).astype(np.float32) * (np.arange(24) < 12)[:, None, None]
    cfg = FeatureCodecConfig(dtype, "request", max_bytes=budget, rank=rank, fill=fill)
    calls, original = [], codec._encode
    monkeypatch.setattr(codec, "_encode", lambda *a: calls.append(1) or original(*a))
    found = encode_features(features, confidence, grid, cfg, request)
    assert found.budget_bytes <= budget and len(calls) <= 9  # bisection: about 12 over 1,728 or 3,456 candidates
    monkeypatch.setattr(codec, "_encode", original)
    score = confidence * request
    order = np.argsort(-score.reshape(-1), kind="stable")
    candidates = order if fill else order[: np.count_nonzero(score)]
    if fill:  # what no ego asked for after, most confident first
        asked, rest = np.split(order, [np.count_nonzero(score)])
        candidates = np.concatenate([asked, rest[np.argsort(-confidence.reshape(-1)[rest], kind="stable")]])
    basis = codec._basis(features, np.sort(candidates), rank)

    def size(k: int) -> int:
        return codec._encode(features, confidence, grid, cfg, np.sort(candidates[:k]), basis).budget_bytes

    largest = max(k for k in range(len(candidates) + 1) if size(k) <= budget)
    assert found.num_voxels <= largest <= found.num_voxels + max(1, found.num_voxels >> codec.SIZE_NOISE_SHIFT)


def test_request_selects_where_the_ego_asks():
    grid, features, confidence = _volume(2)
    request = np.zeros(grid.dims, np.float32)
    request[:4] = 1.0  # the ego needs only the first 4 x-slices (384 voxels)
    enc = encode_features(features, confidence, grid, FeatureCodecConfig("int8", "request", max_bytes=6000), request)
    sent = np.argwhere(decode_features(enc).confidence > 0)
    assert len(sent) > 50 and (sent[:, 0] < 4).all()
    # without a request a vehicle falls back to its own confidence, as "topk"
    fallback = encode_features(features, confidence, grid, FeatureCodecConfig("int8", "request", max_bytes=6000))
    topk = encode_features(features, confidence, grid, FeatureCodecConfig("int8", "topk", max_bytes=6000))
    assert fallback == topk


@pytest.mark.parametrize("rank", [0, 8])
def test_fill_spends_what_the_requests_leave_on_the_most_confident_others(rank):
    grid, features, confidence = _volume(4)
    request = np.zeros(grid.dims, np.float32)
    request[:2] = 1.0  # 192 voxels asked for: a third of a 20 KB budget
    asked = request.reshape(-1) > 0

    def sent(cfg: FeatureCodecConfig) -> np.ndarray:
        return decode_features(encode_features(features, confidence, grid, cfg, request)).confidence.reshape(-1) > 0

    only = FeatureCodecConfig("int8", "request", max_bytes=20000, rank=rank)
    fill = dataclasses.replace(only, fill=True)
    assert (sent(only) == asked).all()  # without fill the rest of the budget goes unspent
    filled = sent(fill)
    assert encode_features(features, confidence, grid, fill, request).budget_bytes <= 20000
    assert filled[asked].all() and filled.sum() > 2 * asked.sum()
    others = confidence.reshape(-1)[~asked]
    assert others[filled[~asked]].min() >= others[~filled[~asked]].max()  # then the sender's most confident
    # a budget the requests overflow: the same voxels as without fill, the best-asked
    tight = dataclasses.replace(only, max_bytes=1800)
    assert (sent(dataclasses.replace(tight, fill=True)) == sent(tight)).all() and sent(tight).sum() < asked.sum()
    assert fill.name == ("int8-request19KB-fill-pca8-zstd" if rank else "int8-request19KB-fill-zstd")
    with pytest.raises(CodecError, match="fill needs selection 'request' and a max_bytes budget"):
        FeatureCodecConfig("int8", "request", fill=True)
    with pytest.raises(CodecError, match="fill must be true or false"):
        FeatureCodecConfig("int8", "request", max_bytes=1000, fill=1)


def test_budget_and_request_are_checked():
    grid, features, confidence = _volume()
    with pytest.raises(CodecError, match="max_bytes needs selection"):
        FeatureCodecConfig("int8", "dense", max_bytes=1000)
    with pytest.raises(CodecError, match="max_bytes must be"):
        FeatureCodecConfig("int8", "topk", max_bytes=-1)
    with pytest.raises(CodecError, match="even an empty selection"):
        encode_features(features, confidence, grid, FeatureCodecConfig("int8", "topk", max_bytes=10))
    with pytest.raises(CodecError, match="request: a"):
        encode_features(
            features, confidence, grid, FeatureCodecConfig("int8", "request"), np.full(grid.dims, 2.0, np.float32)
        )
    assert FeatureCodecConfig("int8", "request", max_bytes=65536).name == "int8-request64KB-zstd"


# --- transform coding: the message's own principal directions (rank) ----------------------------------------------


def _low_rank(seed: int, rank: int, channels: int = 32, dims=(16, 16, 6)):
    """Features lying exactly on a `rank`-dimensional affine subspace of the channels (plus confidence)."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(channels, rank))
    coefficients = rng.normal(size=(rank, int(np.prod(dims)))) * np.linspace(3, 1, rank)[:, None]
    features = (directions @ coefficients + rng.normal(size=(channels, 1))).astype(np.float32).reshape(channels, *dims)
    return _grid(dims), features, rng.uniform(size=dims).astype(np.float32)


@pytest.mark.parametrize("dtype", list(FEATURE_DTYPES))
@pytest.mark.parametrize("selection", ["dense", "topk", "request"])
def test_rank_wire_layout_decodes_independently(dtype, selection):
    """values carry K coefficient rows; basis (C x K, row-major) and mean rebuild the channels, as the .msg says."""
    grid, features, confidence = _volume(3, channels=12)
    rank = 5
    cfg = FeatureCodecConfig(dtype, selection, topk=300, rank=rank)
    enc = encode_features(features, confidence, grid, cfg, np.ones(grid.dims, np.float32))
    n = enc.num_voxels
    assert (enc.basis_rank, enc.rows, len(enc.basis), len(enc.basis_mean)) == (rank, rank, 12 * rank, 12)
    assert enc.values_raw_size == (-(-rank * n // 2) if dtype == "int4" else rank * n * FEATURE_DTYPES[dtype].itemsize)
    assert len(enc.quant_scale) == (rank if dtype in QUANT_LEVELS else 0)
    assert enc.budget_bytes == enc.payload_bytes + 4 * (len(enc.quant_scale) + len(enc.quant_offset) + 12 * rank + 12)
    wire = _wire_values(_raw_field(enc.values, enc.codec, FEATURE_DTYPES[dtype].itemsize), dtype, rank, n).astype(
        np.float64
    )
    if dtype in QUANT_LEVELS:
        wire = (
            wire * np.asarray(enc.quant_scale, np.float64)[:, None] + np.asarray(enc.quant_offset, np.float64)[:, None]
        )
    basis = np.asarray(enc.basis, np.float64).reshape(12, rank)
    np.testing.assert_allclose(basis.T @ basis, np.eye(rank), atol=1e-6)  # orthonormal directions
    rebuilt = basis @ wire + np.asarray(enc.basis_mean, np.float64)[:, None]
    dec = decode_features(enc)
    np.testing.assert_allclose(dec.features.reshape(12, -1)[:, dec.mask.reshape(-1)], rebuilt, rtol=1e-6, atol=1e-6)
    plain = decode_features(
        encode_features(
            features, confidence, grid, FeatureCodecConfig(dtype, selection, topk=300), np.ones(grid.dims, np.float32)
        )
    )
    np.testing.assert_array_equal(dec.mask, plain.mask)  # the same voxels: transform coding changes only their values
    np.testing.assert_array_equal(dec.confidence, plain.confidence)


@pytest.mark.parametrize("rank", [1, 3, 8])
def test_rank_is_lossless_on_features_of_that_rank(rank):
    grid, features, confidence = _low_rank(4, rank)
    dec = decode_features(encode_features(features, confidence, grid, FeatureCodecConfig("float32", rank=rank)))
    np.testing.assert_allclose(dec.features, features, atol=1e-4 * np.abs(features).max())


def test_rank_error_is_the_discarded_variance_and_falls_with_rank():
    """Float32 coefficients on the K principal directions: the squared error is the variance PCA leaves out."""
    grid, features, confidence = _volume(5, channels=16)
    flat = features.reshape(16, -1).astype(np.float64)
    centred = flat - flat.mean(axis=1, keepdims=True)
    discarded = np.linalg.eigvalsh(centred @ centred.T)[::-1]  # descending
    errors = []
    for rank in (1, 4, 8, 16):
        dec = decode_features(encode_features(features, confidence, grid, FeatureCodecConfig("float32", rank=rank)))
        errors.append(((dec.features.reshape(16, -1) - flat) ** 2).sum())
        np.testing.assert_allclose(errors[-1], discarded[rank:].sum(), rtol=1e-3, atol=1e-3)
    assert errors == sorted(errors, reverse=True) and errors[-1] < 1e-6 * errors[0]


def test_rank_fits_more_voxels_under_a_budget():
    grid, features, confidence = _low_rank(6, 6, dims=(32, 32, 6))
    plain = encode_features(features, confidence, grid, FeatureCodecConfig("int8", "topk", max_bytes=20000))
    coded = encode_features(features, confidence, grid, FeatureCodecConfig("int8", "topk", max_bytes=20000, rank=6))
    assert coded.budget_bytes <= 20000 and plain.num_voxels * 2.5 < coded.num_voxels < grid.num_voxels


def test_rank_errors_name_the_field():
    with pytest.raises(CodecError) as info:
        FeatureCodecConfig(rank=-1)
    _assert_error(info, CodecError, "rank")
    grid, features, confidence = _volume(7, channels=4)
    with pytest.raises(CodecError) as info:
        encode_features(features, confidence, grid, FeatureCodecConfig(rank=5))
    _assert_error(info, CodecError, "rank 5", "4 feature channels")
    assert FeatureCodecConfig("int8", "request", max_bytes=65536, rank=8).name == "int8-request64KB-pca8-zstd"
    spread = np.zeros((16, 2, 1, 1), np.float32)
    spread[:, 1] = 60000.0  # within float16 per channel; the one coefficient, +-30000 x sqrt(16), is not
    with pytest.raises(CodecError) as info:
        encode_features(spread, None, _grid((2, 1, 1)), FeatureCodecConfig("float16", rank=1))
    _assert_error(info, CodecError, "float16 range")
    enc = encode_features(features, confidence, grid, FeatureCodecConfig("float32", rank=2))
    for bad, fragment in (
        (dict(basis=enc.basis[:-1]), "basis"),
        (dict(basis_mean=()), "basis"),
        (dict(basis_rank=5, basis=enc.basis * 3), "basis_rank"),
    ):
        with pytest.raises(SizeMismatchError) as info:
            decode_features(dataclasses.replace(enc, **bad))
        _assert_error(info, SizeMismatchError, fragment)
    for field in ("basis", "basis_mean"):
        values = list(getattr(enc, field))
        values[0] = float("nan")
        with pytest.raises(NonFiniteError) as info:
            decode_features(dataclasses.replace(enc, **{field: tuple(values)}))
        _assert_error(info, NonFiniteError, field)


def test_request_maps_with_fewer_levels_take_fewer_bytes_and_keep_what_is_asked():
    grid = GridSpec(ORIGIN, 0.2, (32, 32, 4))
    rng = np.random.default_rng(5)
    need = np.where(rng.random(grid.dims) < 0.1, rng.random(grid.dims), 0.02).astype(np.float32)
    sizes = {}
    for levels in (256, 16, 4, 2):
        enc = codec.encode_request(need, grid, levels=levels)
        got = codec.decode_request(enc)
        sizes[levels] = len(enc.need)
        assert enc.levels == levels and np.abs(got - need).max() <= 0.5 / (levels - 1) + 1e-6
        assert np.array_equal(got * (levels - 1), np.rint(got * (levels - 1)))  # on the levels
    assert np.array_equal(codec.decode_request(codec.encode_request(need, grid, levels=2)), need > 0.5)
    assert sizes[2] < sizes[4] < sizes[16] < sizes[256]
    for levels in (0, 1, 257):
        with pytest.raises(CodecError, match="levels"):
            codec.encode_request(need, grid, levels=levels)
    bad = dataclasses.replace(codec.encode_request(need, grid), levels=2)  # values up to 255 sent as 2 levels
    with pytest.raises(CodecError, match="beyond its 2 levels"):
        codec.decode_request(bad)
    with pytest.raises(CodecError, match="levels"):
        codec.decode_request(dataclasses.replace(bad, levels=0))
