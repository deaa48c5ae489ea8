"""Inference runtime: how a loaded model runs (device, precision, compiled kernels)."""

from co3sop_nodes.inference.path import (
    DEVICES,
    PRECISIONS,
    InferencePath,
    cpu_bfloat16_unit,
    inference_path,
    resolve_device,
)

__all__ = ["DEVICES", "PRECISIONS", "InferencePath", "cpu_bfloat16_unit", "inference_path", "resolve_device"]
