"""`area3d run` keeps to itself: with no ROS_DOMAIN_ID it picks a free domain, discovery stays on
this machine, and episodes started at the same time do not see each other. It also drives a graph
under a namespace."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
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


def test_a_run_on_a_given_domain_where_its_nodes_run_already_is_refused_before_it_starts(tmp_path):
    """With ROS_DOMAIN_ID given (a robot's shell exports one), a graph running there already
    would answer the run's requests in place of the graph it starts (a run did: its budget and
    frames were the other graph's, reported as a success): refused, naming the nodes, before any
    node of its own starts. A node of another name, or of the same name in another namespace,
    is no clash."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from area3d_bringup.episode_config import GraphInUse
    from area3d_bringup.runner import EpisodeConfig, run_episode
    from area3d_msgs_py import middleware
    from area3d_msgs_py.spinning import Spinner

    context = rclpy.Context()
    rclpy.init(context=context)  # the test's domain, given by ROS_DOMAIN_ID
    others = [
        rclpy.create_node("planner", context=context),  # another graph's, serving
        rclpy.create_node("perception", namespace="/robot2", context=context),
        rclpy.create_node("driver", context=context),
    ]
    executor = SingleThreadedExecutor(context=context)
    for node in others:
        executor.add_node(node)
    spinner = Spinner(executor, name="others")
    try:
        domain = int(os.environ["ROS_DOMAIN_ID"])
        assert middleware.domain_in_use(domain)
        config = EpisodeConfig(
            scene="single_object", policy="uniform", budget=BUDGET, seed=0, out_dir=tmp_path,
            run_name="clash", record=False,
        )  # fmt: skip
        with pytest.raises(GraphInUse) as refused:
            run_episode(config)
        message = str(refused.value)
        assert message.startswith(f"nodes planner run already on ROS_DOMAIN_ID={domain} in ")
        assert "--nodes none" in message and "--resume" not in message
        log = (tmp_path / "clash" / "nodes.log").read_text()
        assert f"ROS_DOMAIN_ID={domain}" in log and "[planner]" not in log  # nothing launched
    finally:
        spinner.stop()
        for node in others:
            node.destroy_node()
        context.try_shutdown()


# once spun, the node takes the first look's request too, whose client is gone by then: rclpy
# warns that its answer found nobody
@pytest.mark.filterwarnings("ignore:failed to send response")
def test_a_node_discovery_lists_but_that_answers_nothing_is_no_graph_in_the_way():
    """Discovery lists a killed process's nodes until their lease ends, and a node created and
    never spun (a test's, a crashed tool's): neither answers, neither would plan, so neither keeps
    a run from starting its graph (a run was refused for such a `perception`). Once the same node
    answers, it is one."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from area3d_bringup.episode_config import GraphInUse
    from area3d_bringup.mission_manager import MissionManager
    from area3d_msgs_py.spinning import Spinner

    contexts = [rclpy.Context(), rclpy.Context()]
    for context in contexts:
        rclpy.init(context=context)
    silent = rclpy.create_node("planner", context=contexts[0])  # listed, never spun
    manager = MissionManager(None, context=contexts[1])
    executor = SingleThreadedExecutor(context=contexts[1])
    executor.add_node(manager)
    spinner = Spinner(executor, name="manager")
    try:
        manager.refuse_a_running_graph({"planner", "sim_bridge"}, 0)  # no error: nobody answers
        assert ("planner", "/") in manager.get_node_names_and_namespaces()  # yet it is listed
        answering = SingleThreadedExecutor(context=contexts[0])
        answering.add_node(silent)
        other = Spinner(answering, name="planner")
        try:
            with pytest.raises(GraphInUse, match="nodes planner run already"):
                manager.refuse_a_running_graph({"planner", "sim_bridge"}, 0)
        finally:
            other.stop()
    finally:
        spinner.stop()
        manager.destroy_node()
        silent.destroy_node()
        for context in contexts:
            context.try_shutdown()
