"""The core is ROS-free: only co3sop_nodes.ros may import rclpy or generated messages."""

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


def core_modules() -> list[str]:
    names = [
        info.name
        for info in pkgutil.walk_packages([str(PACKAGE_DIR)], prefix="co3sop_nodes.")
        if not (info.name == GLUE or info.name.startswith(GLUE + "."))
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
