"""A mission beside a robot stack the project did not write: perception, semantics and the planner
as node processes, a plain-rclpy driver process (`robot_driver.py`, no project imports) that
renders the scene as a RealSense-like camera on a moving body, and a mission manager (this module)
that sends the driver to the initial views, then asks NextBestView for one view at a time and
drives there. `area3d bench robot` and the robot tests run it.

The driver's topics are its own, remapped onto the graph's as the README tells a robot's user
(`robot_odometry.yaml`); with `tf` the poses come from /tf (map -> odom with a localisation
offset -> base_link -> the camera's optical frame on /tf_static) and every pose is in `map`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from area3d_bench.soak import rss_mb
from area3d_bringup.launch_description import (
    GRAPH_NODES,
    build_graph,
    default_params_file,
    load_parameters,
    scene_parameters,
)
from area3d_bringup.launcher import Launcher
from area3d_msgs_py import codecs, middleware, msgs, qos, services, topics
from area3d_msgs_py.codecs.views import ViewAnswer
from area3d_msgs_py.probe import Probe
from sim_bridge.scenes import load_scene

DRIVER = Path(__file__).parent / "robot_driver.py"
WAIT_S = 180.0  # processes, DDS and software rendering on a loaded 2-core machine
# each node's time to stop on SIGINT before SIGTERM (the launcher's default is 5 s): with the
# driver streaming on, a loaded 2-core machine took longer once; how fast nodes stop is measured
# in tests/test_shutdown.py, not here
STOP_GRACE_S = 30.0
# a triggered camera's frame not fused after this long is taken as lost on the way (best effort:
# a frame sent while a reader is still being matched never arrives) and captured again
RETRIGGER_S = 15.0
# the driver's topics (a RealSense driver's names), remapped onto the graph's
REMAPS = {
    topics.COLOR.name: "/camera/camera/color/image_raw",
    topics.DEPTH.name: "/camera/camera/aligned_depth_to_color/image_raw",
    topics.CAMERA_INFO.name: "/camera/camera/color/camera_info",
    topics.ODOMETRY.name: "/odom",
}
ROBOT_PARAMS = default_params_file().parent / "robot_odometry.yaml"
# with the driver's /tf: every pose in map, through the localisation's map -> odom
TF_PARAMS = {"world_frame": "map", "pose_source": "tf"}


@dataclass
class MissionOptions:
    """What the driver does and how the mission runs."""

    scene: str = "single_object"
    planned: int = 3  # views asked for after the initial ones, one at a time
    stream_hz: float = 0.0  # 0: one frame per view (a triggered camera)
    tf: bool = False  # poses on /tf in map (else odometry in odom)
    loss: float = 0.0  # share of the driver's images and camera infos never published
    render_scale: float = 1.0  # the driver renders at this fraction of 848x480
    move_s: float = 0.6  # the body's drive from view to view
    seed: int = 0
    # the driver's middleware: "default" (Fast DDS' own settings, as a driver that knows nothing
    # of this project runs) or "area3d" (this project's profile: a 32 MB shared-memory segment)
    driver_profile: str = "area3d"
    sync_timeout_s: float = 5.0  # the planner's wait for a request's frame
    planner: dict = field(default_factory=dict)  # planner parameters on top of the file's


@dataclass
class MissionResult:
    """What the mission saw: every answer (with the seconds it took), the planner's last
    status and grid, each node's last status, and what the driver says it sent."""

    frame: str
    answers: list[tuple[ViewAnswer, float]]
    spent: ViewAnswer
    planner_status: dict
    statuses: dict[str, dict]
    grid: Any
    captures: list[int]
    driver: dict
    log: list[str]
    exit_codes: dict
    retriggers: int = 0  # triggered frames captured again: the first never fused
    # each node process's resident memory (MB) at the first view request and at the end
    rss_mb: dict[str, tuple[float, float]] = field(default_factory=dict)


class Mission:
    """The mission manager: goals to the driver, NextBestView to the planner."""

    def __init__(self, probe: Probe, launcher: Launcher, lines: list[str], frame: str) -> None:
        self.probe, self.launcher, self.lines, self.frame = probe, launcher, lines, frame
        self.goal = probe.publisher(msgs.PoseStamped, "/driver/goal", qos.reliable())
        self.captured = probe.listen(msgs.String, "/driver/captured", qos.reliable())
        self.status = {
            name: probe.listen(msgs.String, topic.name, qos.frames())
            for name, topic in (
                ("planner", topics.PLANNER_STATUS),
                ("perception", topics.PERCEPTION_STATUS),
                ("semantics", topics.SEMANTICS_STATUS),
                ("reconstruction", topics.RECONSTRUCTION_STATUS),
            )
        }
        self.client = None
        self.retriggers = 0  # triggered frames captured again (the first never fused)
        self.grids = probe.listen(
            msgs.PointCloud2, topics.UNCERTAINTY_GRID.name, topics.UNCERTAINTY_GRID.qos()
        )

    def wait_until(self, predicate, timeout_s: float) -> bool:
        """Wait for `predicate`; False past `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while not predicate():
            self.launcher.check()  # a node that died fails here, by name
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True

    def wait(self, predicate, what: str) -> None:
        """Wait for `predicate`; past WAIT_S an AssertionError naming `what`, with the nodes'
        last lines printed."""
        if not self.wait_until(predicate, WAIT_S):
            print("\n".join(self.lines[-60:]))  # what the nodes said, with the failure
            raise AssertionError(f"waited {WAIT_S:.0f} s for {what}")

    def last_status(self, node: str) -> dict:
        messages = self.status[node]
        return json.loads(messages[-1].data) if messages else {}

    def drive(self, T_camera: np.ndarray, wait_fused: bool) -> int:
        """Send the driver's camera to the pose; the stamp of its capture there (with
        `wait_fused`, once the planner fused it: a triggered camera's one frame per view, captured
        again after `RETRIGGER_S` without it, as a mission manager does with a lossy camera)."""
        if not wait_fused:
            return self._goal(T_camera, None)
        for _ in range(int(WAIT_S / RETRIGGER_S)):
            try:
                return self._goal(T_camera, RETRIGGER_S)
            except TimeoutError:
                self.retriggers += 1
        try:
            return self._goal(T_camera, WAIT_S)
        except TimeoutError as err:
            print("\n".join(self.lines[-60:]))  # what the nodes said, with the failure
            raise AssertionError(f"waited {WAIT_S:.0f} s: {err}") from err

    def _goal(self, T_camera: np.ndarray, fuse_s: float | None) -> int:
        """One goal to the driver and the stamp of its capture there; with `fuse_s`, once the
        planner has fused a frame more, or TimeoutError after `fuse_s`."""
        goal_ns = time.time_ns()
        fused = self.last_status("planner").get("frames_fused", 0)
        self.goal.publish(
            msgs.PoseStamped(
                header=codecs.header(goal_ns, self.frame), pose=codecs.matrix_to_pose(T_camera)
            )
        )

        def captured() -> list:
            return [
                json.loads(m.data) for m in self.captured if json.loads(m.data)["goal"] == goal_ns
            ]

        self.wait(captured, f"the driver's capture at {T_camera[:3, 3]}")
        if fuse_s is not None and not self.wait_until(
            lambda: self.last_status("planner").get("frames_fused", 0) > fused, fuse_s
        ):
            raise TimeoutError(f"the frame at {T_camera[:3, 3]} was not fused in {fuse_s} s")
        return captured()[0]["stamp_ns"]

    def ask(self, T: np.ndarray, stamp: int) -> tuple[ViewAnswer, float]:
        """One request, sent once (as a mission manager calls: a request is a view handed out),
        its answer and the seconds it took."""
        request = codecs.view_request_to_msg(1, T, stamp, self.frame)
        if self.client is None:
            self.client = self.probe.node.create_client(msgs.NextBestView, topics.SELECT_VIEWS.name)
            assert self.client.wait_for_service(timeout_sec=WAIT_S), "no select_views service"
        t0 = time.perf_counter()
        try:
            answer = services.call(self.client, request, WAIT_S, resend_s=WAIT_S)
        except TimeoutError:
            print("\n".join(self.lines[-60:]))  # what the nodes said
            print({node: self.last_status(node) for node in self.status})
            raise
        return codecs.msg_to_view_answer(answer), time.perf_counter() - t0


def run_mission(options: MissionOptions, workdir: Path) -> MissionResult:
    """The whole mission: the graph and the driver started, the initial views, `planned` views
    asked for and driven to, one more request (the budget's answer), everything stopped."""
    scene = load_scene(options.scene)
    region = scene_parameters(scene.name)["planner"]
    frame = "map" if options.tf else "odom"
    budget = len(scene.initial_views) + options.planned
    pose = TF_PARAMS if options.tf else {}
    planner = {
        **region,
        **pose,
        "budget": budget,
        "sync_timeout_s": options.sync_timeout_s,
        **options.planner,
    }
    specs = build_graph(
        load_parameters(ROBOT_PARAMS),
        {
            # a streaming driver's rate, as its user sets it: frames missing from the stream
            # count against it (a triggered camera has none)
            "perception": {
                **pose,
                **({"camera_rate_hz": options.stream_hz} if options.stream_hz > 0 else {}),
            },
            "planner": planner,
            "semantics": {"num_initial_views": len(scene.initial_views)},
            "reconstruction": {
                **{key: region[key] for key in ("roi_min", "roi_max", "level")},
                **pose,
            },
        },
        nodes=tuple((n, m) for n, m in GRAPH_NODES if n != "sim_bridge"),
    )
    remaps = [arg for ours, theirs in REMAPS.items() for arg in ("-r", f"{ours}:={theirs}")]
    lines: list[str] = []
    launcher = Launcher(specs, workdir, log_sink=lines.append, ros_args=remaps)
    # the graph's readers of each driver topic: colour and depth perception and semantics,
    # camera info perception and the planner, odometry perception and the planner
    readers = {REMAPS[t.name]: 2 for t in (topics.COLOR, topics.DEPTH, topics.CAMERA_INFO)}
    if not options.tf:
        readers[REMAPS[topics.ODOMETRY.name]] = 2
    config = {
        "scene": str(scene.mjcf_path),
        "readers": readers,
        "stream_hz": options.stream_hz,
        "tf": options.tf,
        "loss": options.loss,
        "render_scale": options.render_scale,
        "move_s": options.move_s,
        "seed": options.seed,
    }
    env = dict(os.environ)
    for name in middleware.PROFILE_ENV_VARS:
        env.pop(name, None)
    if options.driver_profile == "area3d":
        env.update(middleware.transport_env("shm"))
    driver = subprocess.Popen(
        [sys.executable, str(DRIVER), json.dumps(config)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=workdir,
    )
    # initial views in the driver's fixed frame (the scene's are in the world = odom; with tf,
    # map = odom moved by the localisation offset, so the same place in map is the scene's pose)
    probe = Probe("mission_manager")
    answers: list[tuple[ViewAnswer, float]] = []
    captures: list[int] = []
    try:
        mission = Mission(probe, launcher, lines, frame)
        launcher.start()
        assert probe.wait_for_readers(mission.goal, 1, WAIT_S), "the driver never subscribed"
        T, stamp = scene.initial_views[0], 0
        triggered = options.stream_hz <= 0
        for T in scene.initial_views:  # O_0, where the operator put the camera
            stamp = mission.drive(T, triggered)
            captures.append(stamp)
        rss_first = {name: _rss(p.pid) for name, p in launcher.processes.items()}
        rss: dict = {}
        for _ in range(options.planned):
            answer, seconds = mission.ask(T, stamp)
            answers.append((answer, seconds))
            if not answer.success:
                break
            T = answer.views[0]
            stamp = mission.drive(T, triggered)  # the driver drives there and captures
            captures.append(stamp)
        spent, _ = mission.ask(T, stamp)
        mission.wait(lambda: mission.grids, "the uncertainty grid")
        time.sleep(1.0)  # the statuses after the last request
        # the driver streams on: each node's status is read after the planner's, so a count
        # upstream is never older than what the planner fused from it
        heard = {node: len(mission.status[node]) for node in mission.status}
        planner_status = mission.last_status("planner")
        mission.wait(
            lambda: all(len(mission.status[n]) > heard[n] for n in heard if n != "planner"),
            "every node's status after the planner's",
        )
        statuses = {node: mission.last_status(node) for node in mission.status}
        statuses["planner"] = planner_status
        grid = mission.grids[-1]
        retriggers = mission.retriggers
        rss = {name: (rss_first.get(name), _rss(p.pid)) for name, p in launcher.processes.items()}
    finally:
        probe.close()
        codes = launcher.stop(grace_s=STOP_GRACE_S)
        driver.terminate()
        try:
            output, _ = driver.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            driver.kill()
            output, _ = driver.communicate()
    sent = [line for line in output.splitlines() if line.startswith('{"frames_published"')]
    if "Traceback" in output:
        raise AssertionError(f"the driver failed:\n{output[-3000:]}")
    return MissionResult(
        frame=frame,
        answers=answers,
        spent=spent,
        planner_status=planner_status,
        statuses=statuses,
        grid=grid,
        captures=captures,
        driver=json.loads(sent[-1]) if sent else {},
        log=lines,
        exit_codes=codes,
        rss_mb=rss,
        retriggers=retriggers,
    )


def _rss(pid: int) -> float:
    try:
        return rss_mb(pid)
    except OSError:  # the process has ended
        return float("nan")


def aimed_at(T: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_range: float) -> bool:
    """The optical axis (z) of pose T meets the box [lo, hi] within max_range."""
    origin, direction = T[:3, 3], T[:3, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (lo - origin) / direction, (hi - origin) / direction
    near = np.nanmax(np.minimum(a, b))
    far = np.nanmin(np.maximum(a, b))
    return bool(far >= max(near, 0.0) and max(near, 0.0) <= max_range)


def occupied_in_region(grid: Any, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N, 3) centres of the grid's occupied voxels inside the box [lo, hi]."""
    cloud = codecs.msg_to_pointcloud(grid)
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
    inside = np.all((xyz >= lo) & (xyz <= hi), axis=1)
    return xyz[inside & (cloud["occupancy"] > 0)]
