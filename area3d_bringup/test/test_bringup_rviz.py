"""The RViz configuration: installed with the package, relative topic names that the graph
publishes (so it follows the namespace RViz starts in), grid boxes the size of the grid's voxels."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from area3d_bringup.launch_description import build_graph, load_parameters
from area3d_bringup.rviz import config_text, grid_voxel_size, installed_config
from area3d_msgs_py import topics
from area3d_planner.markers import HARD_REGIONS_NS, VIEWS_NS

PACKAGE = Path(__file__).resolve().parents[1]


def _displays(text: str) -> dict[str, dict]:
    config = yaml.safe_load(text)
    return {d["Name"]: d for d in config["Visualization Manager"]["Displays"]}


def _planner(overrides: dict | None = None) -> dict:
    specs = build_graph(load_parameters(), overrides)
    return next(s for s in specs if s.name == "planner").parameters


def test_the_installed_config_is_the_one_generated_for_the_bundled_defaults():
    voxel = grid_voxel_size(_planner())
    assert voxel == pytest.approx(0.01)  # object level (DESIGN.md)
    assert installed_config().read_text() == config_text(voxel)


def test_the_config_is_installed_with_the_package_by_pip_and_colcon():
    assert installed_config().is_file() and installed_config().parent.name == "rviz"
    setup = ast.parse((PACKAGE / "setup.py").read_text())
    data_files = next(
        ast.literal_eval(k.value)
        for n in ast.walk(setup)
        if isinstance(n, ast.Call)
        for k in n.keywords
        if k.arg == "data_files"
    )
    assert ("share/area3d_bringup/rviz", ["rviz/area3d.rviz"]) in data_files
    pyproject = (PACKAGE.parent / "pyproject.toml").read_text()
    assert '"rviz/*"' in pyproject


def test_topics_are_relative_names_the_graph_publishes_with_matching_durability():
    displays = _displays(installed_config().read_text())
    expected = {
        "Uncertainty grid": (topics.UNCERTAINTY_GRID.name, "Transient Local"),
        "Planned views": (topics.VIEW_MARKERS.name, "Transient Local"),
        "Hard regions": (topics.HARD_REGION_MARKERS.name, "Transient Local"),
        "Reconstruction": (topics.RECONSTRUCTION_MESH.name, "Transient Local"),
        "Next views": (topics.NEXT_VIEWS.name, "Volatile"),
        "Camera": (topics.COLOR.name, "Volatile"),
    }
    for name, (topic, durability) in expected.items():
        assert displays[name]["Topic"]["Value"] == topic and not topic.startswith("/")
        assert displays[name]["Topic"]["Durability Policy"] == durability
    # each marker display shows the namespace the planner draws its markers in (markers.py)
    for name, namespace in (("Planned views", VIEWS_NS), ("Hard regions", HARD_REGIONS_NS)):
        assert displays[name]["Class"] == "rviz_default_plugins/MarkerArray"
        assert displays[name]["Namespaces"] == {namespace: True}
    assert displays["Reconstruction"]["Class"] == "rviz_default_plugins/Marker"
    assert displays["Reconstruction"]["Namespaces"] == {"reconstruction": True}
    grid = displays["Uncertainty grid"]
    assert (grid["Style"], grid["Channel Name"]) == ("Boxes", "uncertainty")


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        ({"sim_bridge": {"scene": "living_room"}}, 0.05),  # room level (DESIGN.md)
        ({"sim_bridge": {"scene": "single_object"}, "planner": {"voxel_size": 0.02}}, 0.02),
    ],
)
def test_the_grids_boxes_are_its_voxels(overrides, expected):
    voxel = grid_voxel_size(_planner(overrides))
    assert voxel == pytest.approx(expected)
    assert _displays(config_text(voxel))["Uncertainty grid"]["Size (m)"] == pytest.approx(expected)


def test_a_voxel_budget_that_coarsens_the_grid_coarsens_the_boxes():
    room = {"sim_bridge": {"scene": "living_room"}}
    coarse = grid_voxel_size(_planner({**room, "planner": {"voxel_budget": 20_000}}))
    assert coarse > grid_voxel_size(_planner(room))


def test_area3d_rviz_writes_the_config_of_a_launch_and_the_command_for_its_namespace(tmp_path):
    out = tmp_path / "room.rviz"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "area3d_bringup.cli",
            "rviz",
            *("--scene", "living_room", "--out", str(out), "--namespace", "/robot1"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert f"rviz2 -d {out} --ros-args -r __ns:=/robot1" in result.stdout
    assert _displays(out.read_text())["Uncertainty grid"]["Size (m)"] == pytest.approx(0.05)
