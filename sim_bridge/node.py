"""sim_bridge node: a simulated RGB-D camera that captures a frame at every goal pose it is sent.

Subscribes /area3d/camera/goal_pose (PoseStamped, optical frame in `world`); publishes color,
depth, camera_info, the capture pose, TF (world -> camera_link -> camera_optical_frame) and a
status line per goal.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.node import Node, run_node
from sim_bridge.camera import R_LINK_OPTICAL, SimCamera, link_from_optical
from sim_bridge.scenes import load_scene

WORLD_FRAME = "world"
LINK_FRAME = "camera_link"
OPTICAL_FRAME = "camera_optical_frame"

GOAL_TOPIC = "/area3d/camera/goal_pose"
COLOR_TOPIC = "/area3d/camera/color/image_raw"
DEPTH_TOPIC = "/area3d/camera/depth/image_raw"
INFO_TOPIC = "/area3d/camera/camera_info"
POSE_TOPIC = "/area3d/camera/pose"
STATUS_TOPIC = "/area3d/camera/status"


class SimBridgeNode:
    """Wires parameters and topics around `SimCamera`."""

    NODE_NAME = "sim_bridge"

    def __init__(self, node: Node) -> None:
        self.node = node
        scene_name = node.declare_parameter("scene", "single_object")
        width = int(node.declare_parameter("width", 640))
        height = int(node.declare_parameter("height", 480))
        hfov_deg = float(node.declare_parameter("hfov_deg", 90.0))  # paper, Sec. 4: FOV 90 deg
        max_range = float(node.declare_parameter("max_range", 5.0))  # paper, Sec. 4: 5 m
        clearance = float(node.declare_parameter("clearance", 0.05))
        depth_noise = bool(node.declare_parameter("depth_noise", False))
        self.scene = load_scene(scene_name)
        self.camera = SimCamera(
            self.scene, width, height, hfov_deg, max_range, clearance, depth_noise
        )
        self.pub_color = node.create_publisher("sensor_msgs/msg/Image", COLOR_TOPIC)
        self.pub_depth = node.create_publisher("sensor_msgs/msg/Image", DEPTH_TOPIC)
        self.pub_info = node.create_publisher("sensor_msgs/msg/CameraInfo", INFO_TOPIC)
        self.pub_pose = node.create_publisher("geometry_msgs/msg/PoseStamped", POSE_TOPIC)
        self.pub_status = node.create_publisher("std_msgs/msg/String", STATUS_TOPIC)
        self.pub_tf = node.create_publisher("tf2_msgs/msg/TFMessage", "/tf")
        self.pub_tf_static = node.create_publisher(
            "tf2_msgs/msg/TFMessage", "/tf_static", latched=True
        )
        T_link_opt = np.eye(4)
        T_link_opt[:3, :3] = R_LINK_OPTICAL
        self.pub_tf_static.publish(
            msgs.TFMessage(
                transforms=[_transform(T_link_opt, node.now_ns(), LINK_FRAME, OPTICAL_FRAME)]
            )
        )
        node.create_subscription("geometry_msgs/msg/PoseStamped", GOAL_TOPIC, self.on_goal)
        node.get_logger().info(
            f"scene {self.scene.name!r} ({self.scene.level}), {width}x{height}, hfov {hfov_deg} deg, waiting for {GOAL_TOPIC}"
        )

    def on_goal(self, msg: Any) -> None:
        stamp_ns = codecs.stamp_to_ns(msg.header.stamp) or self.node.now_ns()
        try:
            T = codecs.pose_to_matrix(msg.pose)
        except InputError as exc:
            self._refuse(stamp_ns, f"goal pose {exc}")
            return
        capture = self.camera.capture(T)
        if not capture.ok:
            self._refuse(stamp_ns, capture.reason)
            return
        self.pub_color.publish(codecs.image_to_msg(capture.rgb, "rgb8", stamp_ns, OPTICAL_FRAME))
        self.pub_depth.publish(codecs.image_to_msg(capture.depth, "32FC1", stamp_ns, OPTICAL_FRAME))
        self.pub_info.publish(
            codecs.intrinsics_to_camera_info(
                self.camera.K, self.camera.width, self.camera.height, stamp_ns, OPTICAL_FRAME
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

    def _refuse(self, stamp_ns: int, reason: str) -> None:
        self.node.get_logger().warning(f"goal at stamp {stamp_ns} refused: {reason}")
        self._status(stamp_ns, False, reason)

    def _status(self, stamp_ns: int, ok: bool, reason: str) -> None:
        self.pub_status.publish(
            msgs.String(data=json.dumps({"stamp_ns": stamp_ns, "ok": ok, "reason": reason}))
        )


def _transform(T: np.ndarray, stamp_ns: int, parent: str, child: str) -> Any:
    return msgs.TransformStamped(
        header=codecs.header(stamp_ns, parent),
        child_frame_id=child,
        transform=codecs.matrix_to_transform(T),
    )


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(SimBridgeNode, argv, name=SimBridgeNode.NODE_NAME)


if __name__ == "__main__":
    raise SystemExit(main())
