"""sim_bridge node: a simulated RGB-D camera that captures a frame at every goal pose it is sent.

Subscribes area3d/camera/goal_pose (PoseStamped, optical frame in `world`); publishes color,
depth, camera_info, the capture pose, a status line per goal, TF (/tf world -> camera_link at each
frame's stamp, /tf_static camera_link -> camera_optical_frame) and its counters (captures, refused
goals by reason, frames waiting for their readers) as diagnostics on /diagnostics. Topics:
`area3d_msgs_py/topics.py`; names are
relative: `__ns` moves them all.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections import Counter, deque
from collections.abc import Sequence
from typing import Any

import numpy as np
from rclpy.node import Node

from area3d_msgs_py import codecs, msgs, topics
from area3d_msgs_py.depth_sensor import RgbdSensorParams
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.guard import Rejections, guarded
from area3d_msgs_py.inputs import check_frame_id, check_stamp
from area3d_msgs_py.lens import distortion
from area3d_msgs_py.lifecycle import PublishGate, exit_process, run_node
from area3d_msgs_py.parameters import (
    MAX_STAMP_AHEAD_PARAM,
    Param,
    declare_parameters,
    params_of,
    report_unknown_parameters,
)
from area3d_msgs_py.status import StatusPublisher
from sim_bridge.camera import (
    R_LINK_OPTICAL,
    STEREO_BASELINE,
    Capture,
    SimCamera,
    link_from_optical,
    right_from_left,
)
from sim_bridge.scenes import load_scene

WORLD_FRAME = "world"
LINK_FRAME = "camera_link"
OPTICAL_FRAME = "camera_optical_frame"
RIGHT_OPTICAL_FRAME = "camera_right_optical_frame"

# The readers.* parameters: the frame topics whose graph readers the first capture waits for.
READER_TOPICS = {
    "color": topics.COLOR,
    "depth": topics.DEPTH,
    "camera_info": topics.CAMERA_INFO,
    "pose": topics.POSE,
    "right": topics.RIGHT_IMAGE,
    "right_camera_info": topics.RIGHT_CAMERA_INFO,
}
BAD_GOAL = "bad_goal"  # a goal message refused before its pose is checked (rejected input)
# While the first frame waits for its readers, they are looked for this often, seconds.
READERS_POLL_S = 0.01

PARAMS = (
    Param("scene", "single_object", "bundled scene name or path to a MuJoCo MJCF file"),
    Param("width", 640, "image width, pixels", range=(8, 8192)),
    Param("height", 480, "image height, pixels", range=(8, 8192)),
    Param("hfov_deg", 90.0, "horizontal field of view, degrees (paper: 90)", range=(1.0, 179.0)),
    Param("max_range", 5.0, "maximum depth, metres (paper: 5 m)", range=(0.01, 1000.0)),
    Param(
        "clearance",
        0.05,
        "goals closer than this to geometry are refused, metres",
        range=(0.0, 10.0),
    ),
    Param(
        "depth_noise",
        True,
        "add a depth camera's noise to the rendered depth (axial, lateral, flying pixels, "
        "dropouts at edges and grazing angles; sensor.*); false = the renderer's exact depth",
    ),
    Param(
        "image_noise",
        1.0,
        "read noise of the colour images, standard deviation in grey levels (0 = exact)",
        range=(0.0, 64.0),
    ),
    Param(
        "noise_seed",
        0,
        "seed of the depth and image noise (repeatable episodes)",
        range=(0, 2**31 - 1),
    ),
    Param(
        "noise_skip",
        0,
        "noise of this many captures drawn and dropped at the start and after each reset, so the "
        "noise goes on from there (`area3d run --resume`: its saved frames), captures",
        range=(0, 2**31 - 1),
    ),
    # the simulated depth camera's noise model; its range is max_range
    *params_of(RgbdSensorParams, "sensor.", skip=("max_range",)),
    Param("stereo", False, "also render and publish the right image of a rectified stereo pair"),
    Param(
        "lens_d",
        (0.0,) * 5,
        "plumb_bob distortion (k1, k2, p1, p2, k3) of the colour and depth images sent, and of "
        "their camera_info's d, as a driver sends raw images; all 0: a pinhole camera (the "
        "rendering is pinhole either way; the in-process episodes never distort)",
        check=lambda v: (
            None if len(v) == 5 and all(math.isfinite(x) for x in v) else "5 finite coefficients"
        ),
    ),
    Param(
        "stereo_baseline",
        STEREO_BASELINE,
        "stereo baseline, metres (right = left + B along optical x)",
        range=(0.001, 10.0),
    ),
    # Volatile topics drop what is published before a reader has matched, and this node's writers
    # may match a new reader later than other nodes do: the first capture waits until the nodes
    # that read each frame topic are matched (by name, so that other readers do not count).
    *(
        Param(
            f"readers.{key}",
            topic.readers,
            f"node names that must read {topic.name} before the first capture is published",
        )
        for key, topic in READER_TOPICS.items()
    ),
    Param(
        "readers.all",
        ("",),
        "nodes that must read every frame topic and the status as well ('' = none)",
    ),
    Param(
        "readers_timeout_s",
        10.0,
        "longest the first capture waits for its readers, seconds (then it is published anyway)",
        read_only=False,
        range=(0.0, 600.0),
    ),
    MAX_STAMP_AHEAD_PARAM,
)


class SimBridgeNode(Node):
    """Wires parameters and topics around `SimCamera`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("sim_bridge", **kwargs)
        p = declare_parameters(self, PARAMS)
        report_unknown_parameters(self)
        self.scene = load_scene(p["scene"])
        self.lens_d = [float(v) for v in p["lens_d"]]
        self.camera = camera_from_parameters(self.scene, p)
        # None when every coefficient is below lens.ZERO (a driver's 1e-12 is no lens)
        self.lens = distortion(self.camera.K, self.camera.width, self.camera.height, self.lens_d)
        if self.lens is not None and p["stereo"]:
            self.camera.close()
            raise InputError(
                "lens_d", self.lens_d, "all 0 (below 1e-9) with stereo (a pair comes rectified)"
            )
        self.pub_color = self._publisher(topics.COLOR)
        self.pub_depth = self._publisher(topics.DEPTH)
        self.pub_info = self._publisher(topics.CAMERA_INFO)
        self.pub_pose = self._publisher(topics.POSE)
        self.pub_status = self._publisher(topics.CAMERA_STATUS)
        self.gate = PublishGate(self.context.ok)
        self.pub_right = self.pub_right_info = None
        if p["stereo"]:
            self.pub_right = self._publisher(topics.RIGHT_IMAGE)
            self.pub_right_info = self._publisher(topics.RIGHT_CAMERA_INFO)
        self.pub_tf = self._publisher(topics.TF)
        self.pub_tf_static = self._publisher(topics.TF_STATIC)
        T_link_opt = np.eye(4)
        T_link_opt[:3, :3] = R_LINK_OPTICAL
        static = [_transform(T_link_opt, self._now_ns(), LINK_FRAME, OPTICAL_FRAME)]
        if p["stereo"]:
            T_right = right_from_left(np.eye(4), p["stereo_baseline"])
            static.append(_transform(T_right, self._now_ns(), OPTICAL_FRAME, RIGHT_OPTICAL_FRAME))
        self.pub_tf_static.publish(msgs.TFMessage(transforms=static))
        self.required_readers = self._required_readers(p)
        self.readers_matched = False
        # Frames captured before their readers matched, published in order once they have
        # (or once readers_timeout_s has passed): the goal callback never waits.
        self.held: deque[tuple[int, Capture]] = deque()
        self._readers_deadline: float | None = None
        self._readers_timer = self.create_timer(READERS_POLL_S, self._release_when_read)
        self._readers_timer.cancel()
        self.max_stamp_ahead_s = p["max_stamp_ahead_s"]
        self.captures = 0
        self.resets = 0  # area3d/camera/reset calls served
        self.refused: Counter[str] = Counter()  # goals refused, by `validity` kind or bad_goal
        self.diagnostics = StatusPublisher(self, None, self._diagnostic_state)
        # malformed goals, reported in every status line
        self.rejections = Rejections(on_count=self.diagnostics.changed)
        goal = topics.GOAL
        self.create_subscription(
            goal.msg_type,
            goal.name,
            guarded(self, self.on_goal, goal.name, self.rejections),
            goal.qos(),
        )
        self.create_service(topics.CAMERA_RESET.srv_type, topics.CAMERA_RESET.name, self._on_reset)
        self.get_logger().info(
            f"scene {self.scene.name!r} ({self.scene.level}), {p['width']}x{p['height']}, "
            f"hfov {p['hfov_deg']} deg, waiting for {self.resolve_topic_name(goal.name)}"
        )

    def _publisher(self, topic: topics.Topic) -> Any:
        return self.create_publisher(topic.msg_type, topic.name, topic.qos())

    def _required_readers(self, p: dict) -> dict[Any, set[str]]:
        """{publisher: node names that must read it before the first frame goes out}."""
        everyone = {name for name in p["readers.all"] if name}
        required = {
            self.pub_color: set(p["readers.color"]) | everyone,
            self.pub_depth: set(p["readers.depth"]) | everyone,
            self.pub_info: set(p["readers.camera_info"]) | everyone,
            self.pub_pose: set(p["readers.pose"]) | everyone,
        }
        if everyone:  # the status that follows the first frame reaches them too
            required[self.pub_status] = everyone
        # the right camera's topics wait for their own readers only: `readers.all` is who reads
        # a frame (`area3d run`'s mission manager records colour, depth, camera_info and pose),
        # and a reader of the pair's right image is perception's stereo backend
        if p["stereo"]:
            required[self.pub_right] = set(p["readers.right"])
            required[self.pub_right_info] = set(p["readers.right_camera_info"])
        return required

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def on_goal(self, msg: msgs.PoseStamped) -> None:
        stamp_ns = codecs.stamp_to_ns(msg.header.stamp) or self._now_ns()
        try:
            if msg.header.stamp.sec or msg.header.stamp.nanosec:  # 0 = capture now
                check_stamp(msg, self._now_ns(), self.max_stamp_ahead_s)
            check_frame_id(msg, WORLD_FRAME)
            T = codecs.pose_to_matrix(msg.pose)
        except InputError as exc:
            self.rejections.count(topics.GOAL.name, exc.field)
            self._refuse(stamp_ns, f"{topics.GOAL.name}: {exc}", BAD_GOAL)
            return
        capture = self.camera.capture(T)
        if not capture.ok:
            self._refuse(stamp_ns, capture.reason, capture.refusal)
            return
        if self.readers_matched:
            self._publish(stamp_ns, capture)
            return
        self.held.append((stamp_ns, capture))
        if self._readers_deadline is None:  # the first frame: wait for its readers
            timeout_s = self.get_parameter("readers_timeout_s").value
            self._readers_deadline = time.monotonic() + timeout_s
            self._readers_timer.reset()
        self._release_when_read()

    def _on_reset(self, request, response):
        """area3d/camera/reset (std_srvs/Trigger): the noise starts over from noise_seed, frames
        held for their readers are dropped, and the next frame waits for its readers again (a new
        mission manager's), as the first one did."""
        self.camera.reseed()
        held = len(self.held)
        self.held.clear()
        self.readers_matched = False
        self._readers_deadline = None
        self._readers_timer.cancel()
        self.resets += 1
        self.diagnostics.changed()
        response.success = True
        response.message = (
            f"noise from seed {self.camera.seed} again, {held} held frames dropped "
            f"(reset {self.resets})"
        )
        self.get_logger().info(f"{topics.CAMERA_RESET.name}: {response.message}")
        return response

    def _release_when_read(self) -> None:
        """Publish the held frames once their readers have matched, or once readers_timeout_s
        has passed (then with a warning); until then, called again by a timer."""
        missing = self._missing_readers()
        if missing and time.monotonic() <= self._readers_deadline:
            return
        if missing:
            timeout_s = self.get_parameter("readers_timeout_s").value
            self.get_logger().warning(
                f"publishing after {timeout_s} s without these readers: {missing}"
            )
        self._readers_timer.cancel()
        self.readers_matched = True  # later readers are on their own, as with any camera
        while self.held:
            self._publish(*self.held.popleft())

    def _publish(self, stamp_ns: int, capture: Capture) -> None:
        """Publish one capture, unless the node is stopping: a Ctrl-C shuts the context down
        between two callbacks or in the middle of this one, and the publish then raised (a
        traceback as the node exited); the gate takes it as the stop it is."""
        with self.gate as running:
            if running:
                self._send(stamp_ns, capture)

    def _send(self, stamp_ns: int, capture: Capture) -> None:
        T = capture.T_world_cam
        rgb, depth = capture.rgb, capture.depth
        info = codecs.intrinsics_to_camera_info(
            self.camera.K, self.camera.width, self.camera.height, stamp_ns, OPTICAL_FRAME
        )
        if self.lens is not None:  # as the lens would have sent them
            rgb, depth = self.lens.color(rgb), self.lens.depth(depth)
            info.d = self.lens_d
        self.pub_color.publish(codecs.image_to_msg(rgb, "rgb8", stamp_ns, OPTICAL_FRAME))
        self.pub_depth.publish(codecs.image_to_msg(depth, "32FC1", stamp_ns, OPTICAL_FRAME))
        self.pub_info.publish(info)
        if self.pub_right is not None:
            self.pub_right.publish(
                codecs.image_to_msg(capture.rgb_right, "rgb8", stamp_ns, RIGHT_OPTICAL_FRAME)
            )
            self.pub_right_info.publish(
                codecs.intrinsics_to_camera_info(
                    self.camera.K,
                    self.camera.width,
                    self.camera.height,
                    stamp_ns,
                    RIGHT_OPTICAL_FRAME,
                    baseline=self.camera.stereo_baseline,
                )
            )
        self.pub_pose.publish(
            msgs.PoseStamped(
                header=codecs.header(stamp_ns, WORLD_FRAME), pose=codecs.matrix_to_pose(T)
            )
        )
        self.pub_tf.publish(
            msgs.TFMessage(
                transforms=[_transform(link_from_optical(T), stamp_ns, WORLD_FRAME, LINK_FRAME)]
            )
        )
        self._status(stamp_ns, True, "ok")
        self.captures += 1
        self.diagnostics.changed()

    def _diagnostic_state(self) -> dict:
        """The camera's counters, for /diagnostics."""
        waiting = not self.readers_matched and bool(self.held)
        return {
            "node": "sim_bridge",
            "captures": self.captures,
            "resets": self.resets,
            "goals_refused": {"total": sum(self.refused.values()), "by_reason": dict(self.refused)},
            "frames_held_for_readers": len(self.held),
            "readers_matched": self.readers_matched,
            "readers_missing": self._missing_readers() if waiting else {},
            "rejected": self.rejections.snapshot(),
        }

    def _missing_readers(self) -> dict[str, list[str]]:
        """{topic: nodes not matched yet} over the frame topics; a node counts once this node has
        discovered its subscription and the publisher has matched every discovered subscription."""
        missing = {}
        for pub, required in self.required_readers.items():
            subscriptions = self.get_subscriptions_info_by_topic(pub.topic_name)
            lacking = required - {info.node_name for info in subscriptions}
            if not lacking and pub.get_subscription_count() < len(subscriptions):
                lacking = {"(matching)"}
            if lacking:
                missing[pub.topic_name] = sorted(lacking)
        return missing

    def _refuse(self, stamp_ns: int, reason: str, kind: str) -> None:
        self.get_logger().warning(f"goal at stamp {stamp_ns} refused: {reason}")
        self.refused[kind] += 1
        with self.gate as running:  # as in `_publish`
            if running:
                self._status(stamp_ns, False, reason)
        self.diagnostics.changed()

    def _status(self, stamp_ns: int, ok: bool, reason: str) -> None:
        self.pub_status.publish(
            msgs.String(
                data=json.dumps(
                    {
                        "stamp_ns": stamp_ns,
                        "ok": ok,
                        "reason": reason,
                        "rejected": self.rejections.snapshot(),
                    }
                )
            )
        )


def camera_from_parameters(scene: Any, p: dict) -> SimCamera:
    """The camera this node's parameters `p` describe (also what `area3d_bringup.inprocess`
    captures with)."""
    return SimCamera(
        scene,
        p["width"],
        p["height"],
        p["hfov_deg"],
        p["max_range"],
        p["clearance"],
        p["depth_noise"],
        seed=p["noise_seed"],
        image_noise=p["image_noise"],
        noise_skip=p["noise_skip"],
        stereo_baseline=p["stereo_baseline"] if p["stereo"] else 0.0,
        sensor=RgbdSensorParams(
            max_range=p["max_range"],
            **{
                f.name: p[f"sensor.{f.name}"]
                for f in dataclasses.fields(RgbdSensorParams)
                if f.name != "max_range"
            },
        ),
    )


def _transform(T: np.ndarray, stamp_ns: int, parent: str, child: str) -> Any:
    return msgs.TransformStamped(
        header=codecs.header(stamp_ns, parent),
        child_frame_id=child,
        transform=codecs.matrix_to_transform(T),
    )


def main(args: Sequence[str] | None = None) -> int:
    return run_node(SimBridgeNode, "sim_bridge", args)


if __name__ == "__main__":
    exit_process(main())
