"""A robot stack nobody wrote for us: perception, semantics and the planner as node processes
beside a separate plain-rclpy process (tests/clients/robot_driver.py, no project imports) that
plays a RealSense-like RGB-D driver plus the odometry of the body the camera is mounted on. No
sim_bridge: the driver renders the MuJoCo scene itself at each pose NextBestView returns, after
driving its odometry there.

The driver's topics are its own (remapped onto ours), best effort, bgr8 and 16UC1 millimetres at
848x480 with an 87 degree field of view, images stamped independently of a 50 Hz odometry in
`odom`, the camera mounted by /tf_static. The graph runs as the README tells a robot's user to
start it: the bundled `robot_odometry.yaml` (`world_frame: odom`, `pose_source: odometry`,
`camera_qos: sensor_data`, the mount from /tf_static) with the region and workspace of the scene,
and the README's remappings; the grid must build in `odom`, and every view NextBestView returns must
be in `odom`, inside the workspace and aimed at the region."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from area3d_bringup.launch_description import (
    GRAPH_NODES,
    build_graph,
    default_params_file,
    load_parameters,
    scene_parameters,
)
from area3d_bringup.launcher import Launcher
from area3d_msgs_py import codecs, msgs, qos, topics
from area3d_msgs_py.probe import Probe
from sim_bridge.scenes import load_scene

DRIVER = Path(__file__).parent / "clients" / "robot_driver.py"
WAIT_S = 180.0  # processes, DDS and software rendering on a loaded 2-core machine
PLANNED = 3
# the driver's topics (a RealSense driver's names), remapped onto the graph's
REMAPS = {
    topics.COLOR.name: "/camera/camera/color/image_raw",
    topics.DEPTH.name: "/camera/camera/aligned_depth_to_color/image_raw",
    topics.CAMERA_INFO.name: "/camera/camera/color/camera_info",
    topics.ODOMETRY.name: "/odom",
}
ROBOT_PARAMS = default_params_file().parent / "robot_odometry.yaml"


def _aimed_at(T: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_range: float) -> bool:
    """The optical axis (z) of pose T meets the box [lo, hi] within max_range."""
    origin, direction = T[:3, 3], T[:3, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (lo - origin) / direction, (hi - origin) / direction
    near = np.nanmax(np.minimum(a, b))
    far = np.nanmin(np.maximum(a, b))
    return bool(far >= max(near, 0.0) and max(near, 0.0) <= max_range)


class Mission:
    """The test's mission manager: goals to the driver, NextBestView to the planner."""

    def __init__(self, probe: Probe, launcher: Launcher, lines: list[str]) -> None:
        self.probe, self.launcher, self.lines = probe, launcher, lines
        self.goal = probe.publisher(msgs.PoseStamped, "/driver/goal", qos.reliable())
        self.captured = probe.listen(msgs.String, "/driver/captured", qos.reliable())
        self.status = probe.listen(msgs.String, topics.PLANNER_STATUS.name, qos.frames())
        self.grids = probe.listen(
            msgs.PointCloud2, topics.UNCERTAINTY_GRID.name, topics.UNCERTAINTY_GRID.qos()
        )

    def wait(self, predicate, what: str) -> None:
        deadline = time.monotonic() + WAIT_S
        while not predicate():
            self.launcher.check()  # a node that died fails here, by name
            if time.monotonic() > deadline:
                print("\n".join(self.lines[-60:]))  # what the nodes said, with the failure
                raise AssertionError(f"waited {WAIT_S:.0f} s for {what}")
            time.sleep(0.05)

    def fused(self) -> int:
        return json.loads(self.status[-1].data)["frames_fused"] if self.status else 0

    def capture(self, T_odom_camera: np.ndarray) -> int:
        """Send the driver's camera to the pose; its capture stamp once the planner fused it."""
        goal_ns = time.time_ns()
        fused = self.fused()
        self.goal.publish(
            msgs.PoseStamped(
                header=codecs.header(goal_ns, "odom"), pose=codecs.matrix_to_pose(T_odom_camera)
            )
        )

        def captured() -> list:
            return [
                json.loads(m.data) for m in self.captured if json.loads(m.data)["goal"] == goal_ns
            ]

        self.wait(captured, f"the driver's capture at {T_odom_camera[:3, 3]}")
        self.wait(lambda: self.fused() > fused, "the planner fusing the driver's frame")
        return captured()[0]["stamp_ns"]


def test_the_graph_plans_for_a_robot_driver_and_odometry_it_has_never_seen(tmp_path):
    scene = load_scene("single_object")
    region = scene_parameters(scene.name)["planner"]
    budget = len(scene.initial_views) + PLANNED
    specs = build_graph(
        load_parameters(ROBOT_PARAMS),
        {
            "planner": {**region, "budget": budget, "sync_timeout_s": 60.0},
            "semantics": {"num_initial_views": len(scene.initial_views)},
        },
        nodes=tuple((n, m) for n, m in GRAPH_NODES if n != "sim_bridge"),
    )
    assert {spec.name: spec.parameters["world_frame"] for spec in specs if spec.name != "semantics"} == {
        "perception": "odom", "planner": "odom",
    }  # fmt: skip
    remaps = [arg for ours, theirs in REMAPS.items() for arg in ("-r", f"{ours}:={theirs}")]
    lines: list[str] = []
    launcher = Launcher(specs, tmp_path, log_sink=lines.append, ros_args=remaps)
    # every driver topic's graph readers: colour and depth perception and semantics, camera info
    # perception and the planner, odometry perception and the planner
    readers = {REMAPS[t.name]: 2 for t in (topics.COLOR, topics.DEPTH, topics.CAMERA_INFO)}
    readers[REMAPS[topics.ODOMETRY.name]] = 2
    driver = subprocess.Popen(
        [
            sys.executable,
            str(DRIVER),
            json.dumps({"scene": str(scene.mjcf_path), "readers": readers}),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,
    )
    probe = Probe("mission_manager")
    try:
        mission = Mission(probe, launcher, lines)
        launcher.start()
        assert probe.wait_for_readers(mission.goal, 1, WAIT_S), "the driver never subscribed"
        stamp, T = 0, None
        for T in scene.initial_views:  # O_0, where the operator put the camera
            stamp = mission.capture(T)
        assert mission.fused() == len(scene.initial_views)

        lo, hi = np.array(region["roi_min"]), np.array(region["roi_max"])
        ws_lo, ws_hi = np.array(region["workspace_min"]), np.array(region["workspace_max"])
        for _ in range(PLANNED):
            request = codecs.view_request_to_msg(1, T, stamp, "odom")
            answer = codecs.msg_to_view_answer(
                probe.call(msgs.NextBestView, topics.SELECT_VIEWS.name, request, WAIT_S)
            )
            assert answer.success, (answer.message, lines[-30:])
            assert answer.frame_id == "odom" and len(answer.views) == len(answer.gains) == 1
            T = answer.views[0]
            assert np.all(T[:3, 3] >= ws_lo) and np.all(T[:3, 3] <= ws_hi), T
            assert _aimed_at(T, lo, hi, 5.0), T
            assert answer.gains[0] > 0
            stamp = mission.capture(T)  # the driver drives there and captures
        spent = probe.call(
            msgs.NextBestView,
            topics.SELECT_VIEWS.name,
            codecs.view_request_to_msg(1, T, stamp, "odom"),
            WAIT_S,
        )
        assert not spent.success and "budget" in spent.message

        # the grid built in odom, from the driver's frames: occupied voxels in the region
        mission.wait(lambda: mission.grids, "the uncertainty grid")
        grid = mission.grids[-1]
        assert grid.header.frame_id == "odom"
        cloud = codecs.msg_to_pointcloud(grid)
        xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
        inside = np.all((xyz >= lo) & (xyz <= hi), axis=1)
        assert np.count_nonzero(inside & (cloud["occupancy"] > 0)) > 100
        status = json.loads(mission.status[-1].data)
        assert status["frames_fused"] == budget and status["frames_dropped_no_pose"] == {}
        assert status["rejected"]["total"] == 0
        # the candidate views were planned for the driver's camera, from its CameraInfo
        assert status["camera"]["width"] == 848 and status["camera"]["height"] == 480
        assert abs(status["camera"]["hfov_deg"] - 87.0) < 1e-6
    finally:
        probe.close()
        codes = launcher.stop()
        driver.terminate()
        try:
            output, _ = driver.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            driver.kill()
            output, _ = driver.communicate()
    assert all(code == 0 for code in codes.values()), (codes, lines[-20:])
    assert "Traceback" not in output, output[-3000:]
    assert not any("Traceback" in line for line in lines), lines[-40:]


def test_the_readme_and_the_parameter_file_give_these_remappings_and_a_bad_one_is_refused():
    """What the README tells a robot's user to run is what the test above runs."""
    from typer.testing import CliRunner

    from area3d_bringup.cli import app

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    example = ROBOT_PARAMS.read_text()
    for ours, theirs in REMAPS.items():
        assert f"-r {ours}:={theirs}" in readme and f"-r {ours}:={theirs}" in example
    assert "--params area3d_bringup/config/robot_odometry.yaml" in readme
    result = CliRunner().invoke(app, ["launch", "-r", "area3d/odom=/odom"])
    assert result.exit_code != 0
    assert "--remap: got 'area3d/odom=/odom', expected FROM:=TO" in result.output
