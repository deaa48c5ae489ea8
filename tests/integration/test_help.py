"""`--help` on every executable, resolved as `ros2 run` resolves it: exit 0, and the nodes list every parameter
with its default, bounds and description."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from ament_index_python.packages import get_package_prefix
from executables import executable

from co3sop_nodes.ros import ego, vehicle
from co3sop_nodes.ros.lifecycle import AUTOSTART

EXECUTABLES = sorted(p.name for p in Path(get_package_prefix("co3sop_nodes"), "lib", "co3sop_nodes").iterdir())
PARAMS = {"ego": (*ego.PARAMS, AUTOSTART), "vehicle": (*vehicle.PARAMS, AUTOSTART)}


@pytest.mark.parametrize("name", EXECUTABLES)
def test_help_exits_0_and_explains_every_option(name):
    done = subprocess.run([executable(name), "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage:") and "-h, --help" in done.stdout
    for param in PARAMS.get(name, ()):
        line = next((ln for ln in done.stdout.splitlines() if ln.strip().startswith(f"{param.name} ")), None)
        assert line is not None and (
            "required" in line if param.default is None else f"default {param.default!r}" in line
        ), param.name
        assert param.description in done.stdout.replace("\n      ", " ")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["sample_stream", "--rate", "0"], "--rate 0.0: must be above 0"),
        (["sample_stream", "--frames", "-1"], "--frames -1: must be above 0"),
    ],
)
def test_bad_options_are_usage_errors_not_tracebacks(argv, message):
    done = subprocess.run([executable(argv[0]), *argv[1:]], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr, done.stderr
