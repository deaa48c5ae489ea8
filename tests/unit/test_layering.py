"""The package's layers: the core is ROS-free (only co3sop_nodes.ros may import rclpy or generated messages),
and each subpackage imports only the layers below it (doc/architecture.md draws the same picture)."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import co3sop_nodes

PACKAGE_DIR = Path(co3sop_nodes.__file__).resolve().parent
# rclpy, the generated message packages we use, and the ROS Python runtime.
ROS_MODULES = (
    "rclpy",
    "co3sop_msgs",
    "std_msgs",
    "geometry_msgs",
    "sensor_msgs",
    "builtin_interfaces",
    "tf2_msgs",
    "rosgraph_msgs",
    "diagnostic_msgs",
    "rosidl_runtime_py",
    "rpyutils",
    "ament_index_python",
)
GLUE = "co3sop_nodes.ros"
GRAPH_SCRIPTS = {"co3sop_nodes.cli.demo"}  # console scripts that start the node graph


def core_modules() -> list[str]:
    names = [
        info.name
        for info in pkgutil.walk_packages([str(PACKAGE_DIR)], prefix="co3sop_nodes.")
        if not (info.name == GLUE or info.name.startswith(GLUE + ".") or info.name in GRAPH_SCRIPTS)
    ]
    return ["co3sop_nodes", *names]


BLOCKER = """
import importlib.abc, sys
BLOCKED = {blocked!r}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{{name}} is blocked: the core must not import ROS")
sys.meta_path.insert(0, Block())
import importlib
for module in {modules!r}:
    importlib.import_module(module)
"""


def _import_with_ros_blocked(modules: list[str]) -> subprocess.CompletedProcess:
    code = BLOCKER.format(blocked=ROS_MODULES, modules=modules)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_core_imports_with_ros_unimportable():
    modules = core_modules()
    assert {"co3sop_nodes.v2x.codec", "co3sop_nodes.common.grid", "co3sop_nodes.data.synthetic"} <= set(modules)
    result = _import_with_ros_blocked(modules)
    assert result.returncode == 0, result.stderr


def test_blocker_really_blocks_the_glue():
    # The same harness must fail on a module that does need ROS.
    result = _import_with_ros_blocked(["co3sop_nodes.ros.dds"])
    assert result.returncode != 0 and "blocked" in result.stderr


def test_no_core_source_mentions_a_ros_import():
    # Catches lazy imports inside functions, which an import check cannot see.
    offenders = []
    for path in PACKAGE_DIR.rglob("*.py"):
        if path.relative_to(PACKAGE_DIR).parts[0] == "ros":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            offenders += [f"{path.name}: {n}" for n in names if n.split(".")[0] in ROS_MODULES]
    assert not offenders, offenders


# subpackage -> the subpackages it may import (each layer only from layers above it in this list)
LAYERS = {
    "common": set(),
    "kernels": {"common"},
    "model": {"common", "kernels"},
    "v2x": {"common", "kernels"},
    "messages": {"common", "v2x"},
    "data": {"common", "messages", "v2x"},
    "viz": {"common", "kernels", "data", "messages"},
    "sim": {"common", "kernels", "data", "viz"},
    "inference": {"common", "kernels", "model", "v2x", "viz", "sim"},
    "train": {"common", "data", "inference", "model", "v2x"},
    "eval": {"common", "data", "inference", "messages", "model", "train", "v2x", "viz"},
}
LAYERS["ros"] = set(LAYERS)  # the node glue may use every core layer
LAYERS["cli"] = set(LAYERS)  # console scripts: argument parsing, one call into a layer


def imported_subpackages(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        modules = []
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("co3sop_nodes"):
            modules = [node.module] if node.module != "co3sop_nodes" else [f"co3sop_nodes.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            modules = [a.name for a in node.names if a.name.startswith("co3sop_nodes.")]
        found |= {m.split(".")[1] for m in modules if "." in m}
    return found


def test_every_subpackage_has_a_place_in_the_layers():
    subpackages = {p.parent.name for p in PACKAGE_DIR.glob("*/__init__.py")}
    assert subpackages == set(LAYERS), subpackages ^ set(LAYERS)
    assert not [p.name for p in PACKAGE_DIR.glob("*.py") if p.name != "__init__.py"], "modules belong in a subpackage"


def test_the_layers_have_no_cycle():
    done: set[str] = set()
    order = []
    while len(done) < len(LAYERS):
        ready = [k for k, v in LAYERS.items() if k not in done and v - {k} <= done]
        assert ready, f"cycle among {sorted(set(LAYERS) - done)}"
        done |= set(ready)
        order += ready
    assert order[0] == "common"


def test_each_layer_imports_only_the_layers_below_it():
    offenders = []
    for path in PACKAGE_DIR.rglob("*.py"):
        rel = path.relative_to(PACKAGE_DIR).parts
        if len(rel) < 2:
            continue
        layer = rel[0]
        wrong = imported_subpackages(path) - LAYERS[layer] - {layer}
        offenders += [f"{'/'.join(rel)} imports {w}" for w in sorted(wrong)]
    assert not offenders, offenders
