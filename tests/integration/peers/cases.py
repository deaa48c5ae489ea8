"""Seeded payload cases exchanged by the DDS tests, rebuilt identically on each side."""

from __future__ import annotations

from co3sop_nodes.common.classes import NUM_CLASSES
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.data import synthetic
from co3sop_nodes.v2x.codec import FeatureCodecConfig, encode_features, encode_labels

SMALL = GridSpec((-12.8, -12.8, -2.0), 0.8, (32, 32, 16))
FEATURE_25M = GridSpec((-12.8, -12.8, -2.0), 0.4, (64, 64, 12))

# (kind, grid, channels or None, codec settings or label codec, with confidence)
CASES = [
    ("features", SMALL, 16, FeatureCodecConfig("float32", "dense", codec="none"), True),  # ~1 MB
    ("features", SMALL, 64, FeatureCodecConfig("float32", "dense", codec="none"), False),  # ~4 MB
    ("features", FEATURE_25M, 64, FeatureCodecConfig("float16", "topk", topk=4096), True),
    ("features", FEATURE_25M, 32, FeatureCodecConfig("int8", "threshold", threshold=0.5), True),
    ("features", FEATURE_25M, 64, FeatureCodecConfig("int8", "dense"), True),
    ("labels", BENCHMARK_RANGES["25.6m"], None, "none", False),  # ~3 MB
    ("labels", BENCHMARK_RANGES["51.2m"], None, "zstd", True),
    ("labels", BENCHMARK_RANGES["76.8m"], None, "zstd", False),
]


def encoded(index: int):
    """The encoded payload of case `index` (EncodedFeatures or EncodedLabels)."""
    kind, grid, channels, settings, with_conf = CASES[index]
    if kind == "features":
        features, confidence = synthetic.feature_volume(grid, channels, seed=index)
        return encode_features(features, confidence if with_conf else None, grid, settings)
    labels = synthetic.street_labels(grid, seed=index)
    confidence = (labels * 10).astype("uint8") if with_conf else None
    return encode_labels(labels, grid, NUM_CLASSES, confidence=confidence, codec=settings)
