"""The package as a ROS 2 user installs it: package.xml declares what the code imports (under keys rosdep
resolves), and the launch files reference executables, parameters and files that exist."""

from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml
from ament_index_python.packages import get_package_share_directory

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.ros import ego, vehicle
from co3sop_nodes.ros.graph import LOSSLESS, answers_requests, describe
from co3sop_nodes.ros.lifecycle import AUTOSTART

REPO = Path(__file__).resolve().parents[3]
PACKAGE = REPO / "src" / "co3sop_nodes"
LAUNCH_FILES = sorted((PACKAGE / "launch").glob("*.launch.py"))

# ROS packages the code may import: their rosdep key is their name
ROS_PACKAGES = {
    "ament_index_python",
    "builtin_interfaces",
    "co3sop_msgs",
    "diagnostic_msgs",
    "geometry_msgs",
    "launch",
    "launch_ros",
    "lifecycle_msgs",
    "rcl_interfaces",
    "rclpy",
    "rosgraph_msgs",
    "sensor_msgs",
    "std_msgs",
    "tf2_msgs",
}
# Python modules -> rosdep key (what `rosdep install` must provide)
PYTHON_KEYS = {
    "numpy": "python3-numpy",
    "torch": "python3-torch",
    "yaml": "python3-yaml",
    "PIL": "python3-pil",
    "matplotlib": "python3-matplotlib",
    "tqdm": "python3-tqdm",
    "rosbags": "python3-rosbags-pip",
    "trimesh": "python3-trimesh-pip",
    "embreex": "python3-embreex-pip",
    "mcap": "python3-mcap-pip",
    "zstandard": "python3-zstandard-pip",
}
# modules that need another one at run time without naming it: trimesh's Embree ray caster loads embreex
INDIRECT = {"trimesh.ray.ray_pyembree": "embreex"}
# keys of rosdistro's rosdep/python.yaml we use (checked in ros/rosdistro at 662921b, 2026-08-22); any other
# non-ROS key must be defined in the package's rosdep.yaml
ROSDISTRO_KEYS = {
    "python3-numpy",
    "python3-torch",
    "python3-yaml",
    "python3-pil",
    "python3-matplotlib",
    "python3-tqdm",
    "python3-pytest",
    "python3-rosbags-pip",
    "python3-trimesh-pip",
}


def manifest(tag: str) -> set[str]:
    return {e.text.strip() for e in ET.parse(PACKAGE / "package.xml").getroot().iter(tag)}


def imported_modules() -> set[str]:
    """Dotted names of the absolute imports in the package's modules and launch files."""
    names = set()
    for path in [*(PACKAGE / "co3sop_nodes").rglob("*.py"), *LAUNCH_FILES]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.add(node.module)
                names |= {f"{node.module}.{a.name}" for a in node.names}
    return names


def built_message_packages() -> set[str]:
    """Message packages the nodes build by type name ("pkg/msg/Type", through co3sop_nodes.messages)."""
    text = "\n".join(p.read_text() for p in (PACKAGE / "co3sop_nodes").rglob("*.py"))
    return set(re.findall(r'"(\w+)/msg/\w+"', text)) & ROS_PACKAGES


def required_keys() -> set[str]:
    modules = imported_modules()
    tops = {m.split(".")[0] for m in modules} | {INDIRECT[m] for m in modules if m in INDIRECT}
    tops |= built_message_packages()
    tops -= set(sys.stdlib_module_names) | {"co3sop_nodes", "__future__"}
    unknown = tops - ROS_PACKAGES - PYTHON_KEYS.keys()
    assert not unknown, f"imports without a rosdep key here: {sorted(unknown)}: add them to PYTHON_KEYS and package.xml"
    return {PYTHON_KEYS.get(t, t) for t in tops}


def test_package_xml_declares_exactly_what_the_code_imports():
    assert manifest("exec_depend") == required_keys()
    assert "python3-pytest" in manifest("test_depend")


def test_every_python_key_resolves():
    own = yaml.safe_load((PACKAGE / "rosdep.yaml").read_text())
    keys = {k for k in manifest("exec_depend") | manifest("test_depend") if k not in ROS_PACKAGES}
    assert keys <= ROSDISTRO_KEYS | own.keys(), sorted(keys - ROSDISTRO_KEYS - own.keys())
    assert own.keys() <= keys, "rosdep.yaml defines keys nothing uses"
    pinned = {
        re.split(r"[=<>\[]", line)[0].strip().lower()
        for line in (REPO / "ros2_ws" / "requirements.txt").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    }
    for key, rule in own.items():
        packages = rule["ubuntu"]["pip"]["packages"]
        assert set(packages) <= pinned, f"{key}: {packages} not pinned in ros2_ws/requirements.txt"


def test_package_xml_and_rosdep_yaml_are_installed():
    share = Path(get_package_share_directory("co3sop_nodes"))
    assert (share / "package.xml").is_file() and (share / "rosdep.yaml").is_file()
    assert sorted(p.name for p in (share / "launch").glob("*.launch.py")) == [p.name for p in LAUNCH_FILES]


# --- launch files (`launch` is not on PyPI: parsed, not run) ---------------------------------------


def console_scripts() -> set[str]:
    return set(re.findall(r'f"(\w+) = \{PACKAGE\}', (PACKAGE / "setup.py").read_text()))


def config_parameters(executable: str) -> set[str]:
    """Every parameter of the node's parameter file, dotted."""

    def flat(d: dict, prefix: str = "") -> set[str]:
        return set().union(*(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k} for k, v in d.items()))

    return flat(yaml.safe_load((PACKAGE / "config" / f"{executable}.yaml").read_text())["/**"]["ros__parameters"])


NODE_PARAMS = {
    "ego": (*ego.PARAMS, AUTOSTART),
    "vehicle": (*vehicle.PARAMS, AUTOSTART),
}  # lifecycle nodes: autostart too


@pytest.mark.parametrize("executable", sorted(NODE_PARAMS))
def test_parameter_files_list_every_optional_parameter(executable):
    params = NODE_PARAMS[executable]
    assert config_parameters(executable) == {p.name for p in params if p.default is not None}
    assert all(p.description for p in params)


def calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [
        n
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", None)) == name
    ]


def keyword(call: ast.Call, name: str):
    return next((k.value for k in call.keywords if k.arg == name), None)


def test_there_is_a_launch_file_for_the_graph_a_vehicle_and_the_ego():
    assert [p.name for p in LAUNCH_FILES] == ["ego.launch.py", "graph.launch.py", "vehicle.launch.py"]


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_references_exist(path):
    tree = ast.parse(path.read_text(), str(path))
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description" for n in tree.body)
    scripts = console_scripts()
    nodes = calls(tree, "Node")
    assert nodes
    for node in nodes:
        assert ast.literal_eval(keyword(node, "package")) == "co3sop_nodes"
        if not isinstance(keyword(node, "executable"), ast.Constant):  # graph.launch.py: from the graph's description
            assert path.name == "graph.launch.py"
            continue
        executable = ast.literal_eval(keyword(node, "executable"))
        assert executable in scripts, f"{path.name}: no executable {executable}"
        params = keyword(node, "parameters")
        for d in (e for e in (params.elts if params is not None else []) if isinstance(e, ast.Dict)):
            names = {ast.literal_eval(k) for k in d.keys if k is not None}
            if any(k is None for k in d.keys):  # **LOSSLESS settings of the ego's own vehicle
                names |= set(LOSSLESS)
            declared = {p.name for p in NODE_PARAMS[executable]}
            assert names <= declared, f"{path.name}: {executable} has no parameters {names - declared}"
    declared = {ast.literal_eval(c.args[0]) for c in calls(tree, "DeclareLaunchArgument")}
    used = {c.args[0].value for c in calls(tree, "LaunchConfiguration") if isinstance(c.args[0], ast.Constant)}
    used |= {
        c.args[0].value for c in calls(tree, "arg") if isinstance(c.args[0], ast.Constant)
    }  # graph: arg(name) performs one
    assert used <= declared, f"{path.name}: undeclared launch arguments {used - declared}"
    for join in calls(
        tree, "PathJoinSubstitution"
    ):  # parameter files: (share, "config", "x.yaml") or (CONFIG, "x.yaml")
        for part in join.args[0].elts:
            if isinstance(part, ast.Constant) and part.value.endswith(".yaml"):
                assert (PACKAGE / "config" / part.value).is_file(), f"{path.name}: no config/{part.value}"


def test_graph_launch_and_demo_start_the_one_described_graph():
    """Both read the graph from ros/graph.py's `describe`; neither lists nodes of its own."""
    launch = (PACKAGE / "launch" / "graph.launch.py").read_text()
    demo = (PACKAGE / "co3sop_nodes" / "ros" / "demo.py").read_text()
    for text in (launch, demo):
        assert "from co3sop_nodes.ros.graph import" in text and "describe(" in text
    for name in ("recorder", "ego", "vehicle", "player"):
        assert f'executable("{name}")' not in demo and f'executable="{name}"' not in launch


def test_the_described_graph_runs_existing_executables_with_declared_parameters(tmp_path):
    graph = describe(
        tmp_path / "bag",
        [3, 5, 8],
        "lidar",
        tmp_path / "g.mcap",
        0.5,
        common={"checkpoint": "tiny-lidar"},
        vehicle_params={"codec.dtype": "int8"},
    )
    scripts = console_scripts()
    assert [s.executable for s in (*graph.nodes, graph.player)] == [
        "recorder",
        "ego",
        "vehicle",
        "vehicle",
        "vehicle",
        "player",
    ]
    for spec in (*graph.nodes, graph.player):
        assert spec.executable in scripts
        assert set(spec.parameters) <= {p.name for p in NODE_PARAMS.get(spec.executable, ())}, spec
    own, *others = graph.vehicles
    assert own.parameters == {"id": 3, "checkpoint": "tiny-lidar", **LOSSLESS} and own.car == "ego"
    assert [(o.car, o.namespace, o.parameters["codec.dtype"]) for o in others] == [
        ("cav5", "/cav_5", "int8"),
        ("cav8", "/cav_8", "int8"),
    ]
    assert own.ros_arguments()[:3] == ["--ros-args", "-r", "__ns:=/cav_3"] and "id:=3" in own.ros_arguments()
    defaults = {p.name: p.default for p in NODE_PARAMS["vehicle"]}
    assert (defaults["send"], defaults["codec.selection"]) == ("features", "dense")  # as answers_requests takes them
    assert not any(answers_requests(v) for v in graph.vehicles)  # dense: no request maps subscribed
    assert graph.player.arguments[:3] == (str(tmp_path / "bag"), "--rate", "0.5")
    assert "/cav_8/lidar/points" in graph.player.arguments and "/cav_8/camera0/image_raw" not in graph.player.arguments
    # the recorder, off the critical path, yields the CPU to the rest
    assert graph.recorder.prefix == ["nice", "-n", str(graph.recorder.niceness)] and graph.recorder.niceness > 0
    assert all(s.prefix == [] for s in (*graph.egos, *graph.vehicles, graph.player))


def test_every_cav_an_ego_gets_its_own_features_on_board_and_the_others_over_v2x(tmp_path):
    graph = describe(
        tmp_path / "bag",
        [3, 5, 8],
        "lidar",
        tmp_path / "g.mcap",
        0.5,
        egos="all",
        common={"checkpoint": "tiny-lidar"},
        vehicle_params={"codec.selection": "request"},
    )
    assert [s.executable for s in graph.nodes] == ["recorder", "ego", "ego", "ego", "vehicle", "vehicle", "vehicle"]
    assert graph.recorder.car is None and graph.player.car is None  # the machine's side, off the radio
    for e, v, car in zip(graph.egos, graph.vehicles, ("ego", "cav5", "cav8")):
        c = v.parameters["id"]
        assert e.parameters["ego_id"] == c and e.node == f"/cav_{c}/ego" and e.car == v.car == car
        assert v.parameters["local_features"] is True and v.parameters["codec.selection"] == "request"
        assert answers_requests(v)  # so it subscribes to the egos' request maps
        # the ego's own features, named relative to its namespace, come from its car's lossless topic
        assert e.remappings == ((f"cav_{c}/voxel_features", f"/cav_{c}/voxel_features/local"),)
        assert ["-r", f"cav_{c}/voxel_features:=/cav_{c}/voxel_features/local"] == e.ros_arguments()[3:5]
    recorded = [re.compile(t) for t in graph.recorder.arguments[3:]]
    for topic in ("/cav_5/ego/occupancy", "/cav_3/ground_truth/occupancy_50m"):
        assert any(r.fullmatch(topic) for r in recorded), topic
    assert not any(r.fullmatch("/cav_8/ego/occupancy/points") for r in recorded)  # the recorder draws it
    with pytest.raises(Co3sopError, match="egos 'some'"):
        describe(tmp_path / "bag", [3], "lidar", tmp_path / "g.mcap", 0.5, egos="some")


def test_the_license_and_the_citation_are_where_users_look():
    root = PACKAGE.parents[1]
    assert "Apache License" in (root / "LICENSE").read_text() and "Version 2.0" in (root / "LICENSE").read_text()
    for xml in (root / "src").glob("*/package.xml"):
        assert "<license>Apache-2.0</license>" in xml.read_text(), xml
    citation = yaml.safe_load((root / "CITATION.cff").read_text())
    assert citation["license"] == "Apache-2.0" and citation["cff-version"] == "1.2.0"
    assert citation["preferred-citation"]["title"].startswith(
        "A Synthetic Benchmark for Collaborative 3D Semantic Occupancy"
    )


def test_the_docker_command_keeps_the_results_on_the_host():
    root = PACKAGE.parents[1]
    run = re.search(r"docker run [^`]*co3sop`", (root / "README.md").read_text()).group(0)
    assert '-v "$PWD/results:/co3sop/results"' in run
    assert 'VOLUME ["/co3sop/results"]' in (root / "docker" / "Dockerfile").read_text()


def test_the_jazzy_recipe_builds_src_only_and_handles_pep_668():
    """On a Jazzy install the vendored TFMessage-only tf2_msgs must not shadow the system's, and rosdep's pip keys
    need a way past PEP 668 on Ubuntu 24.04: the documented recipe says both, for every pip key package.xml uses."""
    page = (PACKAGE / "doc" / "jazzy.md").read_text()
    recipe = page[page.index("### On a ROS 2 Jazzy install") :]
    builds = [line for line in recipe.splitlines() if line.startswith("colcon build")]
    assert builds and all("--base-paths src" in line for line in builds)
    assert "PIP_BREAK_SYSTEM_PACKAGES=1 rosdep install" in recipe
    pip_keys = set(
        re.findall(r"<exec_depend>(python3-[\w-]+-pip)</exec_depend>", (PACKAGE / "package.xml").read_text())
    )
    skip = re.search(r'--skip-keys "([^"]+)"', recipe).group(1).split()
    assert pip_keys and set(skip) == pip_keys


def test_the_readme_fits_a_screen_and_links_every_doc_page():
    readme = (PACKAGE.parents[1] / "README.md").read_text()
    assert len(readme.splitlines()) <= 60
    assert "ros2_ws/run_demo.sh" in readme and "ros2_ws/run_tests.sh" in readme
    pages = ("jazzy", "nodes", "data-and-training", "real-dataset", "v2x", "hostile-input", "architecture", "status")
    for page in (*pages, "results"):
        assert f"(src/co3sop_nodes/doc/{page}.md)" in readme, page
        assert (PACKAGE / "doc" / f"{page}.md").is_file(), page


def test_the_architecture_page_names_every_subpackage():
    page = (PACKAGE / "doc" / "architecture.md").read_text()
    subpackages = sorted(p.parent.name for p in (PACKAGE / "co3sop_nodes").glob("*/__init__.py"))
    assert subpackages and all(f"| `{name}/` |" in page for name in subpackages), subpackages


def test_colcon_test_runs_the_suite():
    """`colcon test` runs pytest in the package's folder (colcon-core does, for a setup.py whose 'test' extra has
    pytest): its settings must point at the repository's tests, and the workspace's defaults at the package."""
    import configparser

    cfg = configparser.ConfigParser()
    cfg.read(PACKAGE / "setup.cfg")
    paths = [(PACKAGE / p).resolve() for p in cfg["tool:pytest"]["testpaths"].split()]
    assert paths == [REPO / "tests" / "unit", REPO / "tests" / "integration"]
    assert '-m "not heavy"' in cfg["tool:pytest"]["addopts"]
    assert re.search(r'extras_require=\{"test": \["pytest"\]\}', (PACKAGE / "setup.py").read_text())
    defaults = yaml.safe_load((REPO / "ros2_ws" / "colcon_defaults.yaml").read_text())
    assert defaults["test"]["base-paths"] == defaults["build"]["base-paths"] == ["../src"]
