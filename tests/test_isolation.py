"""`area3d run` keeps to itself: with no ROS_DOMAIN_ID it picks a free domain, discovery stays on
this machine, and episodes started at the same time do not see each other. It also drives a graph
under a namespace."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from mcap.reader import make_reader

SMALL = ["-p", "sim_bridge.width=240", "-p", "sim_bridge.height=180"]
SMALL += ["-p", "planner.width=240", "-p", "planner.height=180"]
BUDGET = 5


def _topic_counts(run_dir: Path) -> dict[str, int]:
    counts: dict[str, int] = {}
    (path,) = (run_dir / "bag").glob("*.mcap")
    with path.open("rb") as stream:
        for _, channel, _ in make_reader(stream).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def test_episodes_started_at_once_pick_their_own_domains_and_a_namespaced_graph_runs(tmp_path):
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")
    }
    # two graphs at once (one of them namespaced): each must pick a domain of its own
    runs = {"a": [], "ns": ["--namespace", "/robot1"]}
    procs = {
        name: subprocess.Popen(
            [
                sys.executable,
                "-m",
                "area3d_bringup.cli",
                "run",
                "--budget",
                str(BUDGET),
                "--no-evaluate",
                "--out",
                str(tmp_path / name),
                *SMALL,
                *extra,
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for name, extra in runs.items()
    }
    outputs = {}
    for name, proc in procs.items():
        try:
            outputs[name], _ = proc.communicate(timeout=600)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 0, outputs[name][-3000:]
    episodes = {}
    for name in runs:
        (run_dir,) = (tmp_path / name).iterdir()
        episodes[name] = (run_dir, json.loads((run_dir / "episode.json").read_text()))
    domains = [episode["ros"]["domain_id"] for _, episode in episodes.values()]
    assert len(set(domains)) == len(runs), domains  # each picked a free domain of its own
    for name, (run_dir, episode) in episodes.items():
        assert len(episode["views"]) == BUDGET
        counts = _topic_counts(run_dir)
        prefix = "/robot1/area3d" if name == "ns" else "/area3d"
        # only its own goals and frames: another episode's would show up here
        assert counts[f"{prefix}/camera/goal_pose"] == BUDGET, counts
        assert counts[f"{prefix}/camera/color/image_raw"] == BUDGET, counts
        assert counts[f"{prefix}/perception/depth"] == BUDGET, counts
        assert not [t for t in counts if t.startswith("/area3d") and name == "ns"], counts
        log = (run_dir / "nodes.log").read_text()
        assert "discovery LOCALHOST" in log and "(picked: free)" in log
    assert episodes["ns"][1]["ros"]["namespace"] == "/robot1"
