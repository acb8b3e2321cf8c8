"""The colcon and `ros2 launch` path, checked without a ROS 2 install: every package.xml declares
what its package imports (ROS packages by name, Python libraries by rosdep key), and the launch
file starts the nodes of `area3d_bringup/graph.py` from executables that the packages install,
with the bundled parameter file that colcon installs."""

from __future__ import annotations

import ast
import importlib.util
import sys
import types
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from area3d_bringup.graph import NODES

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = (
    "area3d_msgs_py", "sim_bridge", "area3d_perception", "area3d_semantics", "area3d_planner",
    "area3d_reconstruction", "area3d_bringup", "area3d_eval", "area3d_bench",
)  # fmt: skip
ROS_PACKAGES = {
    "rclpy", "builtin_interfaces", "std_msgs", "std_srvs", "geometry_msgs", "sensor_msgs",
    "nav_msgs", "diagnostic_msgs", "visualization_msgs", "rcl_interfaces", "tf2_msgs",
    "ament_index_python",
    "launch", "launch_ros", "area3d_interfaces",  # the last: this repository's interfaces (CMake)
}  # fmt: skip
# Python imports -> rosdep keys (ros/rosdistro rosdep/python.yaml; "-pip" where Ubuntu 24.04 has
# no package); None: no rosdep key exists, pip installs it from the root pyproject.toml.
ROSDEP_KEYS: dict[str, str | None] = {
    "numpy": "python3-numpy",
    "scipy": "python3-scipy",
    "yaml": "python3-yaml",
    "cv2": "python3-opencv",
    "skimage": "python3-skimage",
    "matplotlib": "python3-matplotlib",
    "PIL": "python3-pil",
    "requests": "python3-requests",
    "urllib3": "python3-urllib3",
    "typer": "python3-typer",
    "rich": "python3-rich",
    "numba": "python3-numba",
    "trimesh": "python3-trimesh-pip",
    "open3d": "python3-open3d-pip",
    "mujoco": "python3-mujoco-pip",
    "rosbags": "python3-rosbags-pip",
    "foxglove": None,
    "libusb_package": None,
}
# optional backends, imported only when selected (the `ml` extra, or not on PyPI at all), and the
# benchmark's engine for several processes or machines (the `cluster` extra)
OPTIONAL = {
    "torch",
    "transformers",
    "vggt",
    "depth_anything_3",
    "gsplat",
    "lpips",
    "dask",
    "distributed",
}
# declared without an import: `ros2 launch` itself
# launched, not imported: `ros2 launch` starts the reconstruction node by its executable
RUNTIME_ONLY = {"area3d_bringup": {"ros2launch", "area3d_reconstruction"}}


def imports(package: str) -> set[str]:
    """Top-level names of every module the package's code imports (tests and setup.py aside),
    at module level or inside functions."""
    names: set[str] = set()
    for path in (ROOT / package).rglob("*.py"):
        if "test" in path.relative_to(ROOT / package).parts or path.name == "setup.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names - set(sys.stdlib_module_names) - {package}


def declared(package: str) -> set[str]:
    root = ET.parse(ROOT / package / "package.xml").getroot()
    assert root.findtext("name") == package
    return {e.text for tag in ("depend", "exec_depend") for e in root.iter(tag)}


@pytest.mark.parametrize("package", PACKAGES)
def test_every_package_xml_declares_what_its_package_imports_and_nothing_else(package):
    needed: set[str] = set()
    for name in imports(package) - OPTIONAL:
        if name in PACKAGES or name in ROS_PACKAGES:
            needed.add(name)
        else:
            assert name in ROSDEP_KEYS, f"{package} imports {name}: add its rosdep key here"
            if ROSDEP_KEYS[name] is not None:
                needed.add(ROSDEP_KEYS[name])
    have = declared(package)
    assert needed - have == set(), f"{package}/package.xml lacks these dependencies"
    assert have - needed - RUNTIME_ONLY.get(package, set()) == set(), "declared, never imported"
    text = (ROOT / package / "package.xml").read_text()
    for name in imports(package):
        if ROSDEP_KEYS.get(name, "") is None:  # pip-only: said so where a reader looks
            assert name.replace("_", "-") in text or name in text


def test_the_packages_depend_on_each_other_without_a_cycle():
    graph = {p: declared(p) & set(PACKAGES) for p in PACKAGES}
    done: set[str] = set()
    while len(done) < len(graph):
        ready = {p for p, deps in graph.items() if p not in done and deps <= done}
        assert ready, f"cycle among {set(graph) - done}"
        done |= ready


class _Recorded:
    """A stand-in for a launch action: remembers how it was built."""

    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


def _stub_launch_modules(monkeypatch) -> None:
    """`launch`, `launch_ros` and `ament_index_python` as recording stand-ins (they are not on
    PyPI; a sourced ROS 2 has the real ones)."""
    modules = {
        "launch": {"LaunchDescription": _Recorded},
        "launch.actions": {"DeclareLaunchArgument": _Recorded},
        "launch.substitutions": {"LaunchConfiguration": _Recorded},
        "launch_ros": {},
        "launch_ros.actions": {"Node": _Recorded},
        "ament_index_python": {},
        "ament_index_python.packages": {
            "get_package_share_directory": lambda package: (
                f"/opt/ws/install/{package}/share/{package}"
            )
        },
    }
    for name, attributes in modules.items():
        module = types.ModuleType(name)
        module.__dict__.update(attributes)
        monkeypatch.setitem(sys.modules, name, module)


def _console_scripts(package: str) -> dict[str, str]:
    tree = ast.parse((ROOT / package / "setup.py").read_text())
    entry_points = next(
        ast.literal_eval(k.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Call)
        for k in n.keywords
        if k.arg == "entry_points"
    )
    return dict(line.replace(" ", "").split("=") for line in entry_points["console_scripts"])


def _data_files(package: str) -> list:
    tree = ast.parse((ROOT / package / "setup.py").read_text())
    return next(
        ast.literal_eval(k.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Call)
        for k in n.keywords
        if k.arg == "data_files"
    )


def test_the_launch_file_starts_the_graphs_nodes_with_the_installed_parameter_file(monkeypatch):
    _stub_launch_modules(monkeypatch)
    path = ROOT / "area3d_bringup" / "launch" / "area3d.launch.py"
    spec = importlib.util.spec_from_file_location("area3d_launch_file", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    (actions,) = description.args
    arguments = {a.args[0]: a.kwargs for a in actions if not a.kwargs.get("package")}
    nodes = [a.kwargs for a in actions if a.kwargs.get("package")]

    assert set(arguments) == {"params_file", "namespace"}
    default = arguments["params_file"]["default_value"]
    assert default == "/opt/ws/install/area3d_bringup/share/area3d_bringup/config/area3d.yaml"
    assert arguments["namespace"]["default_value"] == ""
    # the nodes of graph.py, in its order, each from an executable its package installs
    assert [(n["package"], n["executable"], n["name"]) for n in nodes] == [
        (g.package, g.executable, g.name) for g in NODES
    ]
    for node, graph_node in zip(nodes, NODES, strict=True):
        scripts = _console_scripts(graph_node.package)
        assert scripts[graph_node.executable] == f"{graph_node.module}:main"
        (params,) = node["parameters"]
        assert params.args == ("params_file",) and node["namespace"].args == ("namespace",)
    # colcon installs that parameter file, and it configures exactly the graph's nodes
    config = ("share/area3d_bringup/config", ["config/area3d.yaml", "config/robot_odometry.yaml"])
    assert config in _data_files("area3d_bringup")
    sections = yaml.safe_load((ROOT / "area3d_bringup" / "config" / "area3d.yaml").read_text())
    assert set(sections) == {g.name for g in NODES}


@pytest.mark.parametrize("package", PACKAGES)
def test_colcon_installs_each_packages_manifest_and_index_marker(package):
    data_files = dict(_data_files(package))
    assert data_files[f"share/{package}"] == ["package.xml"]
    assert data_files["share/ament_index/resource_index/packages"] == [f"resource/{package}"]
    assert (ROOT / package / "resource" / package).is_file()
