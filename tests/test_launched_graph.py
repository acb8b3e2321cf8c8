"""`area3d run --nodes none`: the mission manager alone drives a graph that `area3d launch` started
in another process, as a robot's user runs the graph beside their stack and an episode from a
terminal. The graph keeps its map after the episode, so a second episode on it must stop with a
message that says so instead of planning on the first one's frames."""

from __future__ import annotations

import json
import subprocess
import sys

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


def test_an_episode_drives_a_graph_launched_elsewhere_and_a_second_one_refuses_its_map(
    tmp_path, interrupt
):
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
    finally:
        graph_log = interrupt(graph)
    assert first.returncode == 0, (first.stdout[-3000:], first.stderr[-3000:], graph_log[-3000:])
    runs = sorted((tmp_path / "runs").iterdir())
    assert len(runs) == 2
    data = json.loads((runs[0] / "episode.json").read_text())
    assert [v["kind"] for v in data["views"]] == ["initial"] * 4 + ["planned"] * (BUDGET - 4)
    assert data["recorded"]["/area3d/perception/depth"] == BUDGET  # the launched graph's perception
    assert data["planner_status"]["frames_fused"] == BUDGET
    log = (runs[0] / "nodes.log").read_text()
    assert "[mission_manager]" in log
    for node in ("sim_bridge", "perception", "semantics", "planner"):
        assert f"[{node}]" not in log  # started by the launch, not by the episode
        assert f"[{node}]" in graph_log
    # the second episode captured its 4 initial views into a map that already held 6 frames
    assert second.returncode != 0
    said = " ".join((second.stdout + second.stderr).split())
    assert "the planner has fused 10 frames, this episode captured 4" in said, said[-2000:]
    assert "start the graph again for a new episode" in said
    assert "or start it again and continue this one with --resume" in said  # not on this graph
    assert len(json.loads((runs[1] / "episode.json").read_text())["views"]) == 4  # kept
