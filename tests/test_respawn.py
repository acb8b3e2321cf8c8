"""With --respawn, an episode in which each node in turn is killed once still completes without
--resume, and the restarted planner rebuilds everything it had fused."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

# The smallest episode that still plans: |O_0| = 4 plus three planned views, tiny images.
EPISODE = [
    "--scene", "single_object", "--budget", "7", "--no-evaluate", "--no-record",
    "-p", "sim_bridge.width=160", "-p", "sim_bridge.height=120",
    "-p", "planner.width=160", "-p", "planner.height=120",
]  # fmt: skip
# (node, views on disk before it is killed); each kill also waits for the previous restart
KILLS = (("sim_bridge", 1), ("perception", 3), ("semantics", 4), ("planner", 5))
NODE_MODULE = {
    "sim_bridge": "sim_bridge.node",
    "perception": "area3d_perception.node",
    "semantics": "area3d_semantics.node",
    "planner": "area3d_planner.node",
}


@pytest.mark.timeout(600)  # beyond the test's own 300 s deadline, which says what went wrong
def test_each_node_killed_once_is_respawned_and_the_episode_completes(
    tmp_path, child_pids, cmdline
):
    def node_pid(name: str) -> int | None:
        for pid in child_pids(runner.pid):
            if NODE_MODULE[name] in cmdline(pid):
                return pid
        return None

    runner = subprocess.Popen(
        [sys.executable, "-m", "area3d_bringup.cli", "run", *EPISODE, "--out", str(tmp_path),
         "--respawn", "--respawn-delay", "0.5", "--respawn-retries", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    killed: list[str] = []
    try:
        deadline = time.monotonic() + 300
        for name, views in KILLS:
            while runner.poll() is None and time.monotonic() < deadline:
                logs = list(tmp_path.glob("*/nodes.log"))
                log = logs[0].read_text() if logs else ""
                frames = len(list(tmp_path.glob("*/frames/[0-9][0-9][0-9][0-9].npz")))
                previous_back = not killed or f"{killed[-1]} respawned" in log
                pid = node_pid(name)
                if frames >= views and previous_back and pid is not None:
                    os.kill(pid, signal.SIGKILL)
                    killed.append(name)
                    break
                time.sleep(0.05)
        _, err = runner.communicate(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if runner.poll() is None:
            runner.kill()
    assert killed == [name for name, _ in KILLS], f"the episode ended first: {err[-2000:]}"
    assert runner.returncode == 0, err[-3000:]
    (run_dir,) = tmp_path.iterdir()
    episode = json.loads((run_dir / "episode.json").read_text())
    log = (run_dir / "nodes.log").read_text()
    # the reconstruction, not killed here, was never restarted
    assert episode["respawns"] == {name: 1 for name, _ in KILLS} | {"reconstruction": 0}, log[
        -3000:
    ]
    # every view captured once: the budget, in order, none lost or repeated
    views = episode["views"]
    assert [v["kind"] for v in views] == ["initial"] * 4 + ["planned"] * 3
    stamps = [v["stamp_ns"] for v in views]
    assert stamps == sorted(stamps) and len(set(stamps)) == 7
    assert len(list((run_dir / "frames").glob("*.npz"))) == 7
    # the planner that finished the episode (restarted after 5 views) fused all of them, once,
    # and the semantic maps of the initial views
    assert episode["planner_status"]["frames_fused"] == 7, log[-3000:]
    assert episode["planner_status"]["semantic_frames_fused"] == 4, log[-3000:]
    # the runner caught up with every restart (two that happen before its next step are caught
    # up with together: "perception, semantics restarted; ...")
    caught_up = {
        name
        for names in re.findall(r"([a-z_]+(?:, [a-z_]+)*) restarted; bringing the graph up to", log)
        for name in names.split(", ")
    }
    assert caught_up == {name for name, _ in KILLS}, log[-3000:]
