"""The perception node: captured frames in, metric depth + confidence in [0, 1] out.

Subscribes the camera's color, depth, camera info and optical-frame pose, pairs them by stamp
(`StampSync`), runs `FrameEstimator` and publishes depth and confidence with the source frame's
stamp and frame_id.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from typing import Any

from area3d_msgs_py import codecs
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.node import Node, run_node
from area3d_perception.estimator import FEEDFORWARD_WINDOW, FrameEstimator, check_frame
from area3d_perception.frame_sync import MAX_AGE_NS, StampSync
from area3d_perception.sensor_model import RgbdSensorParams

COLOR_TOPIC = "/area3d/camera/color/image_raw"
DEPTH_TOPIC = "/area3d/camera/depth/image_raw"
INFO_TOPIC = "/area3d/camera/camera_info"
POSE_TOPIC = "/area3d/camera/pose"
OUT_DEPTH_TOPIC = "/area3d/perception/depth"
OUT_CONFIDENCE_TOPIC = "/area3d/perception/confidence"
# Complete frames held while no camera info has arrived yet (oldest dropped beyond this).
MAX_FRAMES_WITHOUT_INFO = 8


# Frames arrive in bursts (the initial views); ROS default depth 10 would drop the oldest while
# this node is busy, and every captured frame matters, so frame topics keep a deeper queue.
FRAME_QUEUE_DEPTH = 50


class PerceptionNode:
    """Wires parameters, subscriptions and publishers around `FrameEstimator`."""

    NODE_NAME = "perception"

    def __init__(self, node: Node) -> None:
        self.node = node
        self.log = node.get_logger()
        backend = node.declare_parameter("backend", "rgbd")
        checkpoint = node.declare_parameter("checkpoint", "")
        device = node.declare_parameter("device", "auto")
        noise = bool(node.declare_parameter("noise", False))
        noise_seed = int(node.declare_parameter("noise_seed", 0))
        window = int(node.declare_parameter("window", FEEDFORWARD_WINDOW))
        normalization = node.declare_parameter("confidence_normalization", "inverse")
        self.use_depth = bool(node.declare_parameter("use_depth", True))
        max_age_s = float(node.declare_parameter("sync_max_age_s", MAX_AGE_NS / 1e9))
        sensor_values = {
            f.name: node.declare_parameter(f"sensor.{f.name}", f.default)
            for f in dataclasses.fields(RgbdSensorParams)
        }
        sensor = RgbdSensorParams(**sensor_values)
        self.estimator = FrameEstimator(
            backend=backend,
            sensor=sensor,
            noise=noise,
            noise_seed=noise_seed,
            checkpoint=checkpoint,
            device=device,
            window=window,
            confidence_normalization=normalization,
        )
        keys = ("color", "depth", "pose") if self.use_depth else ("color", "pose")
        self.sync = StampSync(keys, max_age_ns=int(max_age_s * 1e9))
        self.camera: tuple[Any, int, int] | None = None
        self.waiting: deque[tuple[int, dict]] = deque(maxlen=MAX_FRAMES_WITHOUT_INFO)
        self.frames_published = 0

        self.pub_depth = node.create_publisher("sensor_msgs/msg/Image", OUT_DEPTH_TOPIC)
        self.pub_conf = node.create_publisher("sensor_msgs/msg/Image", OUT_CONFIDENCE_TOPIC)
        node.create_subscription(
            "sensor_msgs/msg/Image", COLOR_TOPIC, self.on_color, depth=FRAME_QUEUE_DEPTH
        )
        if self.use_depth:
            node.create_subscription(
                "sensor_msgs/msg/Image", DEPTH_TOPIC, self.on_depth, depth=FRAME_QUEUE_DEPTH
            )
        node.create_subscription(
            "sensor_msgs/msg/CameraInfo", INFO_TOPIC, self.on_camera_info, depth=FRAME_QUEUE_DEPTH
        )
        node.create_subscription(
            "geometry_msgs/msg/PoseStamped", POSE_TOPIC, self.on_pose, depth=FRAME_QUEUE_DEPTH
        )
        self.log.info(f"backend={backend} noise={noise} use_depth={self.use_depth}")

    # inputs ---------------------------------------------------------------------------------
    def on_color(self, msg: Any) -> None:
        self._add("color", msg, codecs.msg_to_image)

    def on_depth(self, msg: Any) -> None:
        self._add("depth", msg, codecs.msg_to_image)

    def on_pose(self, msg: Any) -> None:
        self._add("pose", msg, lambda m: codecs.pose_to_matrix(m.pose))

    def on_camera_info(self, msg: Any) -> None:
        try:
            self.camera = codecs.camera_info_to_intrinsics(msg)
        except InputError as exc:
            self.log.warning(f"camera_info rejected: {exc}")
            return
        while self.waiting:
            stamp, parts = self.waiting.popleft()
            self._process(stamp, parts)

    def _add(self, key: str, msg: Any, decode) -> None:
        stamp = codecs.stamp_to_ns(msg.header.stamp)
        try:
            value = (decode(msg), msg.header.frame_id)
        except InputError as exc:
            self.log.warning(f"{key} at stamp {stamp} rejected: {exc}")
            return
        parts = self.sync.add(key, stamp, value)
        for dropped in self.sync.pop_dropped():
            self.log.warning(f"{dropped.key} at stamp {dropped.stamp_ns} dropped: {dropped.reason}")
        if parts is None:
            return
        if self.camera is None:
            if not self.waiting:
                self.log.warning(
                    f"no camera_info on {INFO_TOPIC} yet; holding frames until it arrives"
                )
            self.waiting.append((stamp, parts))
            return
        self._process(stamp, parts)

    # processing -----------------------------------------------------------------------------
    def _process(self, stamp: int, parts: dict) -> None:
        K, width, height = self.camera
        rgb, color_frame = parts["color"]
        depth, depth_frame = parts["depth"] if "depth" in parts else (None, None)
        T_world_cam, _ = parts["pose"]
        frame_id = depth_frame or color_frame
        try:
            check_frame(rgb, depth, (width, height))
            result = self.estimator.process(rgb, depth, K, T_world_cam)
        except InputError as exc:
            self.log.warning(f"frame at stamp {stamp} rejected: {exc}")
            return
        for note in result.notes:
            self.log.warning(f"frame at stamp {stamp}: {note}")
        self.pub_depth.publish(codecs.image_to_msg(result.depth, "32FC1", stamp, frame_id))
        self.pub_conf.publish(codecs.image_to_msg(result.confidence, "32FC1", stamp, frame_id))
        self.frames_published += 1


def main(argv: list[str] | None = None) -> int:
    """Process entry point: `python -m area3d_perception.node [--ros-args ...]`."""
    return run_node(PerceptionNode, argv, name=PerceptionNode.NODE_NAME)


if __name__ == "__main__":
    raise SystemExit(main())
