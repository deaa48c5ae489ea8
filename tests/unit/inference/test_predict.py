"""The kernels a node compiles before it says it is ready are every kernel its frames use: none waits for a
compiler (or for a library to load) once the node is active."""

import functools
import importlib
import pkgutil

import numpy as np
import pytest
import torch

from co3sop_nodes import kernels
from co3sop_nodes.inference import pace
from co3sop_nodes.inference.checkpoint import load_model, shipped_checkpoint
from co3sop_nodes.inference.predict import compile_kernels, predict_frame
from co3sop_nodes.model.path import inference_path


def _forget_loaded_kernels() -> None:
    """Every kernel module's cached libraries and functions dropped, as in a fresh process."""
    for info in pkgutil.iter_modules(kernels.__path__):
        module = importlib.import_module(f"{kernels.__name__}.{info.name}")
        for value in vars(module).values():
            if callable(getattr(value, "cache_clear", None)) and getattr(value, "__module__", None) == module.__name__:
                value.cache_clear()


@pytest.mark.parametrize("name, precision", [("tiny", "auto"), ("tiny-lidar", "auto"), ("tiny-lidar", "int8")])
def test_a_frame_loads_no_kernel_that_compile_kernels_did_not(name, precision, monkeypatch):
    loaded = []
    load = kernels.load.__wrapped__  # the uncached loader: the disk cache still spares compiling most of them

    @functools.cache
    def recording(source, contract=False, **defines):
        loaded.append((source, tuple(sorted(defines.items()))))
        return load(source, contract, **defines)

    monkeypatch.setattr(kernels, "load", recording)
    _forget_loaded_kernels()
    model, _ = load_model(shipped_checkpoint(f"{name}.pt"))
    model.use(inference_path("cpu", precision))
    assert compile_kernels(model, points=True)
    before = list(loaded)
    with torch.no_grad():
        ego = model.vehicle(**pace.shaped_inputs(model))
        predict_frame(model, ego, np.eye(4), pace.shaped_neighbours(ego))
    assert loaded == before, f"loaded by the first frame only: {sorted(set(loaded) - set(before))}"
