"""The launcher starts each node as its own process, forwards logs, and leaves no orphans."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from area3d_bringup.launch_description import (
    GRAPH_NODES,
    NodeSpec,
    build_graph,
    load_parameters,
    parse_override,
    write_params_file,
)
from area3d_bringup.launcher import Launcher, NodeDied

FAKE_NODE = textwrap.dedent(
    """
    import faulthandler, os, sys, time, signal, yaml
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # as every node (run_node)
    args = sys.argv[1:]
    params_file = args[args.index("--params-file") + 1]
    name = args[args.index("-r") + 1].split(":=")[1]
    params = yaml.safe_load(open(params_file))["/**/" + name]["ros__parameters"]
    signal.signal(signal.SIGINT, lambda *a: (print("clean stop", flush=True), sys.exit(0)))
    if params.get("ignore_sigint"):
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    if params.get("ignore_sigterm"):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    print(f"pid={os.getpid()} params={params}", flush=True)  # up, its SIGINT handling set
    if params.get("die_after_s") is not None:
        time.sleep(params["die_after_s"]); sys.exit(3)
    while True:
        time.sleep(0.05)
    """
)


@pytest.fixture()
def fake_env(tmp_path: Path) -> dict[str, str]:
    (tmp_path / "fake_node.py").write_text(FAKE_NODE)
    return {"PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _catches_sigint(pid: int) -> bool:
    """The process has a SIGINT handler installed (Linux: the SigCgt mask in /proc/PID/status)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) & (1 << (signal.SIGINT - 1)))
    return False


def _pids(launcher: Launcher, timeout_s: float = 60.0) -> dict[str, int]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pids = {
            n: int(line.split("pid=")[1].split()[0])
            for n, lines in launcher.output.items()
            for line in lines
            if "pid=" in line
        }
        if len(pids) == len(launcher.specs):
            return pids
        time.sleep(0.05)
    raise AssertionError(f"nodes did not start: {launcher.output}")


def test_each_node_runs_in_its_own_process_with_its_parameters_and_prefixed_logs(
    tmp_path, fake_env
):
    lines: list[str] = []
    specs = [NodeSpec("alpha", "fake_node", {"x": 1}), NodeSpec("beta", "fake_node", {"y": "two"})]
    launcher = Launcher(specs, tmp_path, env=fake_env, log_sink=lines.append)
    launcher.start()
    try:
        pids = _pids(launcher)
        assert len(set(pids.values()) | {os.getpid()}) == 3
        assert any(line.startswith("[alpha] ") and "'x': 1" in line for line in lines)
        assert any(line.startswith("[beta] ") and "'y': 'two'" in line for line in lines)
    finally:
        codes = launcher.stop()
    assert codes == {"alpha": 0, "beta": 0}, "SIGINT should stop the nodes cleanly"
    assert not any(_alive(pid) for pid in pids.values())


def test_a_node_that_ignores_sigint_is_still_stopped(tmp_path, fake_env):
    specs = [NodeSpec("stubborn", "fake_node", {"ignore_sigint": True})]
    launcher = Launcher(specs, tmp_path, env=fake_env, log_sink=lambda _: None)
    launcher.start()
    pid = _pids(launcher)["stubborn"]
    codes = launcher.stop(grace_s=0.5)
    assert codes["stubborn"] == -signal.SIGTERM
    assert not _alive(pid)


def test_a_node_that_will_not_stop_is_killed_with_its_threads_stacks_in_the_log(tmp_path, fake_env):
    specs = [NodeSpec("hung", "fake_node", {"ignore_sigint": True, "ignore_sigterm": True})]
    lines: list[str] = []
    launcher = Launcher(specs, tmp_path, env=fake_env, log_sink=lines.append)
    launcher.start()
    pid = _pids(launcher)["hung"]
    codes = launcher.stop(grace_s=0.5, dump_wait_s=60)
    assert codes["hung"] == -signal.SIGKILL
    assert not _alive(pid)
    said = lines.index("[launcher] hung did not stop; its threads:")
    # where it hung: the node's main thread in its loop (faulthandler's dump, before the kill)
    assert any(line.startswith("[hung]") and "fake_node.py" in line for line in lines[said:])


def test_death_of_a_node_is_reported_by_name(tmp_path, fake_env):
    specs = [
        NodeSpec("fine", "fake_node", {}),
        NodeSpec("fragile", "fake_node", {"die_after_s": 0.3}),
    ]
    launcher = Launcher(specs, tmp_path, env=fake_env, log_sink=lambda _: None)
    launcher.start()
    try:
        with pytest.raises(NodeDied) as info:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                launcher.check()
                time.sleep(0.05)
        assert info.value.name == "fragile" and info.value.returncode == 3
    finally:
        launcher.stop()


def test_a_dying_node_is_respawned_after_the_delay_until_its_retries_are_spent(tmp_path, fake_env):
    lines: list[str] = []
    specs = [
        NodeSpec("fine", "fake_node", {}),
        NodeSpec("fragile", "fake_node", {"die_after_s": 0.2}),
    ]
    launcher = Launcher(
        specs,
        tmp_path,
        env=fake_env,
        log_sink=lines.append,
        respawn=True,
        respawn_delay_s=0.5,
        respawn_max_retries=2,
    )
    t0 = time.monotonic()
    launcher.start()
    try:
        with pytest.raises(NodeDied) as info:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                launcher.check()  # quiet while a retry is left
                time.sleep(0.05)
        elapsed = time.monotonic() - t0
        assert info.value.name == "fragile" and info.value.returncode == 3
        assert launcher.respawns == {"fine": 0, "fragile": 2}
        fragile_pids = {
            line.split("pid=")[1].split()[0] for line in lines if "[fragile] pid=" in line
        }
        assert len(fragile_pids) == 3  # the first start and two respawns, each a new process
        assert elapsed >= 2 * 0.5  # each respawn waited for the delay
        assert sum("respawning in 0.5 s" in line for line in lines) == 2
        assert launcher.processes["fine"].poll() is None  # the others were never touched
    finally:
        codes = launcher.stop()
    assert codes["fine"] == 0


def _launcher_script(tmp_path, fake_env, node: str, then: str) -> Path:
    """A script that starts a launcher of one fake node `node`, printing its output, then runs
    the lines `then` (names: `launcher`)."""
    script = tmp_path / f"launch_{node}.py"
    script.write_text(
        textwrap.dedent(
            f"""
            import time
            from pathlib import Path
            from area3d_bringup.launcher import Launcher
            from area3d_bringup.launch_description import NodeSpec
            launcher = Launcher([NodeSpec({node!r}, "fake_node", {{}})], Path({str(tmp_path)!r}),
                                env={fake_env!r}, log_sink=lambda l: print(l, flush=True))
            launcher.start()
            """
        )
        + textwrap.dedent(then)
    )
    return script


def test_children_die_with_a_killed_launcher(tmp_path, fake_env):
    script = _launcher_script(tmp_path, fake_env, "orphan", "time.sleep(600)\n")
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    line = parent.stdout.readline()
    child_pid = int(line.split("pid=")[1].split()[0])
    assert _alive(child_pid)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 120  # ends as soon as the node is gone
    while _alive(child_pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(child_pid), "a node outlived its killed launcher"


def test_graph_has_the_four_nodes_with_bundled_defaults_and_overrides():
    specs = build_graph(overrides={"planner": {"eta": 0.5}})
    assert [s.name for s in specs] == [name for name, _ in GRAPH_NODES]
    planner = next(s for s in specs if s.name == "planner")
    assert planner.parameters["eta"] == 0.5
    assert load_parameters()["planner"]["eta"] == 0.3  # the paper's value stays the default


def test_params_file_round_trips_in_ros2_format(tmp_path):
    specs = [NodeSpec("planner", "m", {"eta": 0.3, "policy": "area3d"})]
    path = write_params_file(specs, tmp_path / "p.yaml")
    assert load_parameters(path) == {"planner": {"eta": 0.3, "policy": "area3d"}}


@pytest.mark.parametrize("bad", ["eta=0.3", "planner.eta", ".eta=1", "planner.=1"])
def test_malformed_override_names_the_expected_form(bad):
    with pytest.raises(ValueError, match="NODE.NAME=VALUE"):
        parse_override(bad)


def test_override_values_are_yaml_typed():
    assert parse_override("planner.budget=12") == ("planner", "budget", 12)
    assert parse_override("semantics.backend=none") == ("semantics", "backend", "none")


def test_missing_params_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        load_parameters(tmp_path / "nope.yaml")


def test_nodes_stop_quietly_on_sigint_even_when_the_launcher_ignores_it(tmp_path):
    """A launcher started in the background by a shell inherits SIGINT as ignored; its nodes must
    still stop on the SIGINT it sends them, at once and with exit code 0."""
    specs = build_graph(
        overrides={"sim_bridge": {"width": 64, "height": 48}},
        nodes=(("sim_bridge", "sim_bridge.node"),),
    )
    lines: list[str] = []
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        launcher = Launcher(specs, tmp_path, log_sink=lines.append)
        launcher.start()
    finally:
        signal.signal(signal.SIGINT, previous)
    try:
        deadline = time.monotonic() + 60
        while not any("waiting for" in line for line in lines) and time.monotonic() < deadline:
            launcher.check()
            time.sleep(0.05)
        assert any("waiting for" in line for line in lines), lines
    finally:
        codes = launcher.stop(grace_s=20.0)
    assert codes == {"sim_bridge": 0}, lines[-10:]
    assert not any("Traceback" in line for line in lines)


def test_the_stereo_backend_turns_the_simulated_stereo_pair_on_unless_told_otherwise():
    def sim(overrides):
        return next(s for s in build_graph(overrides=overrides) if s.name == "sim_bridge")

    assert "stereo" not in sim({}).parameters  # mono by default: episodes cost what they did
    assert sim({"perception": {"backend": "stereo"}}).parameters["stereo"] is True
    off = {"perception": {"backend": "stereo"}, "sim_bridge": {"stereo": False}}
    assert sim(off).parameters["stereo"] is False


def test_the_stereo_backend_tells_the_planner_the_nearest_depth_its_disparity_search_reaches():
    def planner(overrides):
        return next(s for s in build_graph(overrides=overrides) if s.name == "planner")

    stereo = {"perception": {"backend": "stereo"}}
    assert "min_range" not in planner({}).parameters  # a depth camera: the yaml's (none)
    # 640 px over 90 degrees: f = 320 px; 6 cm baseline; 96 disparities: 320 * 0.06 / 96 = 0.2 m
    assert planner(stereo).parameters["min_range"] == pytest.approx(0.2)
    # half the image width halves f; matching at half size searches twice the disparities
    narrow = {**stereo, "sim_bridge": {"width": 320}}
    assert planner(narrow).parameters["min_range"] == pytest.approx(0.1)
    coarse = {"perception": {"backend": "stereo", "stereo.downscale": 2}}
    assert planner(coarse).parameters["min_range"] == pytest.approx(0.1)
    wider = {"perception": {"backend": "stereo"}, "sim_bridge": {"stereo_baseline": 0.12}}
    assert planner(wider).parameters["min_range"] == pytest.approx(0.4)
    # a camera class that measures nothing nearer than 0.28 m keeps its own, larger limit
    d435 = {**stereo, "planner": {"min_range": 0.28}}
    assert planner(d435).parameters["min_range"] == pytest.approx(0.28)


def test_with_stereo_a_lone_uncertain_match_makes_no_unknown_space_near_a_surface():
    """The stereo backend's lone matches in the air (a periodic texture at the wrong disparity)
    need a second frame or a confident match to count for `unobserved_reach`; a depth camera's
    lone hit is a surface (the planner's default, 0); a value given is kept."""
    from area3d_bringup.launch_description import STEREO_REACH_CONFIDENCE
    from area3d_planner.config import PlannerConfig

    def planner(overrides):
        return next(s for s in build_graph(overrides=overrides) if s.name == "planner")

    key = "unobserved_reach_confidence"
    assert key not in planner({}).parameters and PlannerConfig().unobserved_reach_confidence == 0
    stereo = {"perception": {"backend": "stereo"}}
    assert planner(stereo).parameters[key] == STEREO_REACH_CONFIDENCE > 0
    assert planner({**stereo, "planner": {key: 0.0}}).parameters[key] == 0.0


def test_perceptions_estimates_are_attached_to_the_frames_they_belong_to(tmp_path):
    import numpy as np

    from area3d_eval.rundir import attach_estimates, iter_frames, read_frame, write_frame

    rgb, depth = np.zeros((4, 6, 3), np.uint8), np.full((4, 6), 2.0, np.float32)
    for index, stamp in enumerate((10, 20)):
        write_frame(tmp_path, index, rgb, depth, np.eye(3), np.eye(4), stamp)
    frames = list(iter_frames(tmp_path))
    estimate = np.full((4, 6), 2.1, np.float32)
    estimates = {20: {"depth": estimate, "confidence": np.ones((4, 6), np.float32)}, 99: {}}

    lines = []
    attach_estimates(tmp_path, frames, estimates, lines.append)
    first, second = (read_frame(tmp_path / "frames" / f"{i:04d}.npz") for i in (0, 1))
    assert first.estimated_depth is None and "view 0" in lines[0]
    np.testing.assert_array_equal(second.estimated_depth, estimate)
    np.testing.assert_array_equal(second.depth, depth)  # the sensor's depth is kept beside it


def test_ctrl_c_stops_a_launcher_started_with_sigint_ignored(tmp_path, fake_env):
    # A parent that ignores SIGINT passes that on to its children, and Python then installs no
    # KeyboardInterrupt handler: the launcher must still stop the graph on Ctrl-C.
    script = _launcher_script(
        tmp_path,
        fake_env,
        "node",
        """
        try:
            launcher.wait()
        finally:
            codes = launcher.stop()
        print(f"stopped {codes}", flush=True)
        """,
    )
    parent = subprocess.Popen(
        [sys.executable, str(script)],
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    assert "pid=" in parent.stdout.readline()  # the node is up ...
    # ... and the launcher waits, Ctrl-C caught: before `wait()` SIGINT is still ignored here
    deadline = time.monotonic() + 60
    while not _catches_sigint(parent.pid):
        assert time.monotonic() < deadline and parent.poll() is None, "the launcher never waited"
        time.sleep(0.01)
    parent.send_signal(signal.SIGINT)
    out, _ = parent.communicate(timeout=120)
    assert parent.returncode == 0, out
    assert "stopped {'node': 0}" in out
