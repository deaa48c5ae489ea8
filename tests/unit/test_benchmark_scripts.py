"""Every benchmark script imports: a name moved in the package and still imported by a script fails here, not when
someone runs the benchmark."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "ros2_ws" / "benchmarks"


@pytest.mark.parametrize("script", sorted(BENCHMARKS.glob("*.py")), ids=lambda p: p.name)
def test_the_script_imports(script, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the scripts import their sibling helpers (timing, ...)
    spec = importlib.util.spec_from_file_location(f"benchmark_{script.stem}", script)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)
    spec.loader.exec_module(module)  # top level only: every script runs its work under `if __name__ == "__main__"`


def test_the_int8_roofline_runs_the_int8_paths_layer(monkeypatch, capsys):
    """`bench_model.py --roofline`'s int8 table builds and times the int8 path's own layer (as model/quantized.py
    makes it), so a change of that layer's signature fails here."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location("benchmark_bench_model", BENCHMARKS / "bench_model.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)
    spec.loader.exec_module(module)
    table = module.int8_table(1, {"float32": 50.0, "bfloat16": 100.0})
    assert len(table.splitlines()) == 5 and "z-outer" in table  # header, rule, three kernels
