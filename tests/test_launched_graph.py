"""`area3d run --nodes none`: the mission manager alone drives a graph that `area3d launch` started
in another process, as a robot's user runs the graph beside their stack and an episode from a
terminal. Each episode first resets the graph's camera, planner and semantics
(area3d/camera/reset, area3d/planner/reset, area3d/semantics/reset), so a second episode on the
same graph plans on its own frames only, and the same episode twice chooses the same views."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import typer

from area3d_bringup.cli import _episode_nodes

BUDGET = 6
SIZE = ["-p", "sim_bridge.width=240", "-p", "sim_bridge.height=180"]
SIZE += ["-p", "planner.width=240", "-p", "planner.height=180"]


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "area3d_bringup.cli", *args]


def test_nodes_none_starts_no_node_and_names_start_only_those():
    assert _episode_nodes("none") == ()
    assert _episode_nodes("") is None
    assert _episode_nodes("semantics, planner") == ("semantics", "planner")
    with pytest.raises(typer.Exit):
        _episode_nodes("none,planner")


def test_episodes_drive_a_graph_launched_elsewhere_each_on_a_reset_map(tmp_path, interrupt):
    # the camera holds its first frame until the mission manager reads its topics (readers.all)
    graph = subprocess.Popen(
        _cli("launch", "--localhost", "-p", "sim_bridge.readers.all=[mission_manager]", *SIZE),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path,
    )  # fmt: skip
    episode = [
        "run", "--nodes", "none", "--budget", str(BUDGET), "--no-evaluate",
        "--out", str(tmp_path / "runs"), *SIZE,
    ]  # fmt: skip
    try:
        first = subprocess.run(
            _cli(*episode), capture_output=True, text=True, timeout=600, cwd=tmp_path
        )
        second = subprocess.run(
            _cli(*episode), capture_output=True, text=True, timeout=600, cwd=tmp_path
        )
        # an episode that would start its own graph on this domain (ROS_DOMAIN_ID is exported)
        # would be answered by the launched one: refused, naming its nodes, none started
        clash = subprocess.run(
            _cli("run", "--budget", str(BUDGET), "--out", str(tmp_path / "clash"), *SIZE),
            capture_output=True, text=True, timeout=600, cwd=tmp_path,
        )  # fmt: skip
    finally:
        graph_log = interrupt(graph)
    domain = os.environ["ROS_DOMAIN_ID"]
    said = " ".join((clash.stdout + clash.stderr).split())
    assert clash.returncode != 0, said[-3000:]
    named = re.search(
        rf"nodes ([a-z_, ]+) run already on ROS_DOMAIN_ID={domain} in namespace /", said
    )
    graph = {"perception", "planner", "reconstruction", "semantics", "sim_bridge"}
    assert named and set(named.group(1).split(", ")) <= graph, said
    launched = " ".join(graph_log.split())  # where the launch says the graph is
    assert re.search(
        rf"on ROS_DOMAIN_ID={domain}, namespace /, transport \w+, discovery LOCALHOST", launched
    )
    for run in (first, second):
        assert run.returncode == 0, (run.stdout[-3000:], run.stderr[-3000:], graph_log[-3000:])
    runs = sorted((tmp_path / "runs").iterdir())
    assert len(runs) == 2
    for n, run_dir in enumerate(runs):
        data = json.loads((run_dir / "episode.json").read_text())
        kinds = ["initial"] * 4 + ["planned"] * (BUDGET - 4)
        assert [v["kind"] for v in data["views"]] == kinds
        assert data["recorded"]["/area3d/perception/depth"] == BUDGET  # the graph's perception
        # the map holds this episode's frames only (the second's: not the first's as well)
        assert data["planner_status"]["frames_fused"] == BUDGET
        assert data["planner_status"]["resets"] == n + 1
        log = (run_dir / "nodes.log").read_text()
        assert "[mission_manager]" in log
        for node in ("sim_bridge", "perception", "semantics", "planner"):
            assert f"[{node}]" not in log  # started by the launch, not by the episode
            assert f"[{node}]" in graph_log
        # what the reset found: nothing before the first episode, its frames before the second
        fused = 0 if n == 0 else BUDGET
        said = " ".join(log.split())
        assert f"planner of the running graph reset: map cleared (reset {n + 1}): {fused} " in said
        assert re.search(r"semantics of the running graph reset: views cleared: \d+ complete", said)
    assert "area3d/planner/reset: map cleared (reset 2): 6 frames fused" in graph_log
    # the same episode twice on one graph: the camera's noise started over, the same views
    first_views, second_views = (
        np.array([v["T_world_cam"] for v in json.loads((d / "episode.json").read_text())["views"]])
        for d in runs
    )
    np.testing.assert_array_equal(first_views, second_views)
