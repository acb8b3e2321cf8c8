"""Every node of the graph exits on SIGINT with code 0 before the launcher would send SIGTERM
(ROS 2 convention: Ctrl-C is a clean stop); the target, 2 s, is printed beside each figure."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import pytest

from area3d_bringup.launch_description import build_graph
from area3d_bringup.launcher import Launcher

# The target is 2 s; a test asserts only the launcher's SIGINT grace (5 s, then SIGTERM), the
# failure this guards against: the time depends on the machine's load and is measured (printed
# here, figures in area3d_msgs_py/README.md), not asserted.
EXIT_BOUND_S = 5.0
# The last line each node logs when it is built (its spin starts right after).
READY_LINE = {
    "sim_bridge": "waiting for",
    "perception": "backend=",
    "semantics": "backend=",
    "planner": "planner ready",
    "reconstruction": "reconstruction ready",
}


def _wait_ready(launcher: Launcher, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        launcher.check()
        if all(
            any(READY_LINE[name] in line for line in launcher.output[name]) for name in READY_LINE
        ):
            return
        time.sleep(0.05)
    raise AssertionError(f"nodes not ready: { {n: o[-3:] for n, o in launcher.output.items()} }")


def _wait_spinning(names, timeout_s: float = 60.0) -> None:
    """Each node answers a parameter service call: it is spinning (the ready line comes a moment
    before, and a signal landing in between is another case)."""
    from rcl_interfaces.srv import ListParameters

    from area3d_msgs_py import services
    from area3d_msgs_py.probe import Probe

    probe = Probe("shutdown_waiter")
    try:
        for name in names:
            client = probe.node.create_client(ListParameters, f"/{name}/list_parameters")
            assert client.wait_for_service(timeout_sec=timeout_s), name
            services.call(client, ListParameters.Request(), timeout_s)  # asked again if lost
    finally:
        probe.close()


def test_each_node_exits_on_sigint_with_code_zero_before_the_sigterm_grace(tmp_path: Path):
    specs = build_graph(
        overrides={
            "sim_bridge": {"width": 160, "height": 120},
            "planner": {"width": 160, "height": 120},
        }
    )
    lines: list[str] = []
    launcher = Launcher(specs, tmp_path, log_sink=lines.append)
    launcher.start()
    exit_s: dict[str, float] = {}
    codes: dict[str, int | None] = {}
    try:
        _wait_ready(launcher)
        _wait_spinning(READY_LINE)
        for name, proc in launcher.processes.items():  # one at a time: each measured alone
            t0 = time.monotonic()
            proc.send_signal(signal.SIGINT)
            try:
                codes[name] = proc.wait(timeout=4 * EXIT_BOUND_S)
            except subprocess.TimeoutExpired:
                codes[name] = None
            exit_s[name] = time.monotonic() - t0
    finally:
        launcher.stop()
    print("exit after SIGINT, s (target 2):", {n: round(t, 3) for n, t in exit_s.items()})
    assert codes == {name: 0 for name in READY_LINE}, (codes, lines[-20:])
    slow = {n: t for n, t in exit_s.items() if t > EXIT_BOUND_S}
    assert not slow, f"nodes slower than {EXIT_BOUND_S} s to exit on SIGINT: {slow}"
    assert not any("Traceback" in line for line in lines), lines[-40:]


def test_a_busy_planner_exits_on_sigint_without_waiting_for_its_work(tmp_path: Path):
    """Frames just fused (a mask rebuild under way) and a request waiting for it: Ctrl-C must not
    wait for the rebuild (it used to, and the planner sometimes needed SIGTERM)."""
    import numpy as np

    from area3d_msgs_py import codecs, msgs, qos
    from area3d_msgs_py.probe import Probe
    from sim_bridge.render import RgbdRenderer
    from sim_bridge.scenes import load_scene

    w, h = 640, 480  # the default camera: a rebuild long enough to land the signal in it
    scene = load_scene("single_object")
    renderer = RgbdRenderer(scene, width=w, height=h)
    views = [(T, renderer.render(T)[1]) for T in scene.initial_views]
    K = renderer.K
    renderer.close()
    specs = build_graph(
        overrides={"planner": {"width": w, "height": h}},
        nodes=(("planner", "area3d_planner.node"),),
    )
    lines: list[str] = []
    launcher = Launcher(specs, tmp_path, log_sink=lines.append)
    probe = Probe("shutdown_probe")
    client = probe.node.create_client(msgs.GetPlan, "area3d/planner/next_best_view")
    pubs = {
        "depth": probe.publisher(msgs.Image, "area3d/perception/depth", qos.graph_frames()),
        "confidence": probe.publisher(
            msgs.Image, "area3d/perception/confidence", qos.graph_frames()
        ),
        "pose": probe.publisher(msgs.PoseStamped, "area3d/camera/pose"),
        "info": probe.publisher(msgs.CameraInfo, "area3d/camera/camera_info"),
    }
    status = probe.listen(msgs.String, "area3d/planner/status")
    launcher.start()
    try:
        assert probe.wait_for(lambda: client.wait_for_service(timeout_sec=0.1), 60)
        assert all(probe.wait_for_readers(pub, 1, 60) for pub in pubs.values())
        for stamp, (T, depth) in enumerate(views, start=1):
            frame_id = "camera_optical_frame"
            pubs["info"].publish(codecs.intrinsics_to_camera_info(K, w, h, stamp, frame_id))
            pubs["pose"].publish(
                msgs.PoseStamped(
                    header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T)
                )
            )
            pubs["depth"].publish(codecs.image_to_msg(depth, "32FC1", stamp, frame_id))
            confidence = np.isfinite(depth).astype(np.float32)
            pubs["confidence"].publish(codecs.image_to_msg(confidence, "32FC1", stamp, frame_id))
        assert probe.wait_for(lambda: any('"frames_fused": 4' in m.data for m in status), 60)
        request = msgs.GetPlan_Request()
        request.start.header = codecs.header(len(views), "world")
        request.start.pose = codecs.matrix_to_pose(views[-1][0])
        request.goal.pose.position.x = 1.0
        client.call_async(request)
        planner = launcher.processes["planner"]
        t0 = time.monotonic()
        planner.send_signal(signal.SIGINT)
        code = planner.wait(timeout=4 * EXIT_BOUND_S)
        exit_s = time.monotonic() - t0
    finally:
        launcher.stop()
        probe.close()
    print(f"busy planner exit after SIGINT: {exit_s:.3f} s")
    assert code == 0, lines[-20:]
    assert exit_s < EXIT_BOUND_S, f"the busy planner took {exit_s:.2f} s to exit on SIGINT"
    assert not any("Traceback" in line for line in lines), lines[-40:]
    # the request the stop ended is no error of the planner's
    assert not any("[ERROR]" in line for line in lines), lines[-40:]


@pytest.mark.parametrize("group", [True, False], ids=["terminal", "process alone"])
def test_ctrl_c_during_an_episode_is_the_users_stop_not_the_planners_failure(
    tmp_path: Path, group: bool
):
    """Ctrl-C in a terminal signals `area3d run` and its nodes together; `kill -INT` or
    `timeout -s INT` signals `area3d run` alone (which ran on to the end: rclpy installs no
    handler for a context of the runner's own, and only the nodes' deaths had stopped it). Either
    way the run says it was interrupted and how to go on, episode.json does not record the
    planner as the reason, and no node ends in a traceback."""
    import json
    import os
    import sys

    out = tmp_path / "runs"
    proc = subprocess.Popen(
        [sys.executable, "-m", "area3d_bringup.cli", "run", "--budget", "40", "--no-evaluate",
         "--no-record", "--out", str(out),
         "-p", "sim_bridge.width=160", "-p", "sim_bridge.height=120",
         "-p", "planner.width=160", "-p", "planner.height=120"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            if len(list(out.glob("*/frames/*.npz"))) >= 6:  # two views planned
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()[0][-3000:]
        if group:
            os.killpg(proc.pid, signal.SIGINT)  # the terminal's Ctrl-C: the whole process group
        else:
            proc.send_signal(signal.SIGINT)
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 2, output[-3000:]
    text = " ".join(output.split())
    assert "error: interrupted (Ctrl-C)" in text and "continue with --resume" in text, text
    (episode,) = out.glob("*/episode.json")
    saved = json.loads(episode.read_text())
    assert saved["stopped_early"] == "" and 6 <= len(saved["views"]) < 40
    # every node stopped quietly: the terminal's SIGINT and then the launcher's own raised
    # KeyboardInterrupt in their teardown, and a capture in flight failed to publish
    log = (episode.parent / "nodes.log").read_text()
    at = log.find("Traceback")
    assert at < 0, log[max(0, at - 300) : at + 3000]
