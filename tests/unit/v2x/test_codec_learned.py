"""Unit tests of the codec's learned mode (ROS-free): a model's wire code sent as its integers, with no
constants, basis or confidence, and every field a hostile sender could set refused by name."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import zstandard

from co3sop_nodes.common.errors import CodecError, SizeMismatchError
from co3sop_nodes.common.grid import GridSpec
from co3sop_nodes.v2x.codec import FeatureCodecConfig, check_codec_for, decode_features, encode_features

GRID = GridSpec((-3.2, -3.2, -1.0), 0.4, (16, 16, 4))
NAME = "0123456789abcdef"


def code_volume(rng, k=4, levels=7):
    """(K, X, Y, Z) integers in [-levels, levels] (mostly small, as a trained code) and a confidence."""
    code = np.clip(np.rint(rng.normal(0, 2, (k, *GRID.dims))), -levels, levels).astype(np.float32)
    return code, rng.uniform(0, 1, GRID.dims).astype(np.float32)


@pytest.mark.parametrize("dtype", ["int4", "int8"])
@pytest.mark.parametrize("selection", ["dense", "topk", "request"])
def test_a_code_goes_as_its_integers(dtype, selection):
    rng = np.random.default_rng(0)
    code, conf = code_volume(rng)
    request = rng.uniform(0, 1, GRID.dims).astype(np.float32)
    cfg = FeatureCodecConfig(dtype=dtype, selection=selection, topk=300, learned=True)
    enc = encode_features(code, conf, GRID, cfg, request, learned_code=NAME)
    assert enc.learned_code == NAME and enc.channels == 4
    assert enc.quant_scale == enc.quant_offset == enc.basis == enc.basis_mean == () and enc.basis_rank == 0
    assert not enc.has_confidence and enc.confidence == b""  # the code carries the confidence
    dec = decode_features(enc)
    assert dec.learned_code == NAME and dec.confidence is None
    sent = dec.mask
    np.testing.assert_array_equal(dec.features[:, sent], code[:, sent])  # exact: integers
    assert np.all(dec.features[:, ~sent] == 0)
    if selection == "request":  # the best-scored voxels (confidence x request)
        score = (conf * request).reshape(-1)
        assert score[sent.reshape(-1)].min() >= np.sort(score)[-300]
    # int4 on the wire: two integers per byte, no constants
    raw = zstandard.ZstdDecompressor().decompress(enc.values)
    assert len(raw) == (-(-4 * enc.num_voxels // 2) if dtype == "int4" else 4 * enc.num_voxels)


def test_a_budget_counts_no_constants_so_more_voxels_fit():
    rng = np.random.default_rng(1)
    code, conf = code_volume(rng)
    learned = encode_features(
        code, conf, GRID, FeatureCodecConfig("int4", "topk", max_bytes=1500, learned=True), learned_code=NAME
    )
    assert learned.budget_bytes <= 1500 and learned.budget_bytes == learned.payload_bytes
    pca = encode_features(code, conf, GRID, FeatureCodecConfig("int4", "topk", max_bytes=1500, rank=4))
    assert learned.num_voxels > pca.num_voxels  # no basis, no per-row constants, no confidence
    check_codec_for(FeatureCodecConfig("int4", "topk", max_bytes=1500, learned=True), 4, GRID)


def test_the_config_refuses_what_a_code_cannot_go_as():
    for bad in ({"dtype": "float16"}, {"dtype": "float32"}, {"dtype": "int4", "rank": 4}):
        with pytest.raises(CodecError, match="learned"):
            FeatureCodecConfig(learned=True, **bad)
    with pytest.raises(CodecError, match="learned must be true or false"):
        FeatureCodecConfig(dtype="int4", learned=1)
    assert FeatureCodecConfig("int4", "request", max_bytes=8192, learned=True).name == "int4-request8KB-learned-zstd"


def test_the_encoder_refuses_values_that_are_not_the_codes_integers():
    rng = np.random.default_rng(2)
    code, conf = code_volume(rng)
    cfg = FeatureCodecConfig(dtype="int4", learned=True)
    with pytest.raises(CodecError, match="learned_code"):
        encode_features(code, conf, GRID, cfg)  # unnamed
    with pytest.raises(CodecError, match=r"integers in \[-7, 7\]"):
        encode_features(code + 0.5, conf, GRID, cfg, learned_code=NAME)
    with pytest.raises(CodecError, match=r"integers in \[-7, 7\]"):
        encode_features(code * 0 + 8, conf, GRID, cfg, learned_code=NAME)
    with pytest.raises(CodecError, match="not learned"):
        encode_features(code, conf, GRID, FeatureCodecConfig(dtype="int4"), learned_code=NAME)


@pytest.mark.parametrize(
    "change, field",
    [
        ({"quant_scale": (1.0,) * 4, "quant_offset": (0.0,) * 4}, "quant_scale"),
        ({"basis_rank": 2, "basis": (0.0,) * 8, "basis_mean": (0.0,) * 4}, "basis"),
        ({"has_confidence": True}, "has_confidence"),
        ({"dtype": "float16"}, "dtype"),
        ({"learned_code": "x" * 65}, "learned_code"),
    ],
)
def test_a_hostile_learned_message_is_refused_by_field(change, field):
    rng = np.random.default_rng(3)
    code, conf = code_volume(rng)
    enc = encode_features(
        code, conf, GRID, FeatureCodecConfig("int4", "topk", topk=50, learned=True), learned_code=NAME
    )
    with pytest.raises(CodecError, match=field):
        decode_features(dataclasses.replace(enc, **change))


def test_integers_beyond_the_dtype_are_refused_on_decode():
    # int8 values of a learned code beyond int4's levels are fine; a code claiming int4 holds at most 7 (and -8,
    # which int4 can pack but no code of 2 * 7 + 1 levels sends)
    code = np.full((2, *GRID.dims), -8.0, np.float32)
    cfg = FeatureCodecConfig(dtype="int8", learned=True)
    enc = encode_features(code, None, GRID, cfg, learned_code=NAME)
    packed = zstandard.ZstdCompressor(write_checksum=True, write_content_size=True).compress(
        (np.full(enc.num_voxels * 2, 0x88, np.uint8)[: -(-enc.num_voxels * 2 // 2)]).tobytes()
    )
    forged = dataclasses.replace(enc, dtype="int4", values=packed, values_raw_size=-(-enc.num_voxels * 2 // 2))
    with pytest.raises(CodecError, match="values"):
        decode_features(forged)
    with pytest.raises(SizeMismatchError):  # a code's integers against another grid
        decode_features(dataclasses.replace(enc, num_voxels=enc.num_voxels - 1))
