"""The planner node: fuses perception (+ semantics) frames and serves next-best-view requests.

Subscribes /area3d/perception/depth, /area3d/perception/confidence, /area3d/camera/pose and
/area3d/camera/camera_info (paired by stamp), /area3d/semantics/uncertainty. Publishes the latched
/area3d/planner/uncertainty_grid, /area3d/planner/status and /area3d/planner/next_views; serves
/area3d/planner/next_best_view (nav_msgs/srv/GetPlan).
"""

from __future__ import annotations

import json
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import fields

import numpy as np

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.node import Node, run_node
from area3d_perception.frame_sync import StampSync
from area3d_planner.cloud import grid_to_msg
from area3d_planner.server import NextBestViewServer, PlannerConfig, PlanRequest

CAMERA_INFO_CACHE = 64


# Frames arrive in bursts (the initial views); ROS default depth 10 would drop the oldest while
# this node is busy, and every captured frame matters, so frame topics keep a deeper queue.
FRAME_QUEUE_DEPTH = 50


class PlannerNode:
    NODE_NAME = "planner"

    def __init__(self, node: Node) -> None:
        self.node = node
        log = node.get_logger()
        values = {}
        for f in fields(PlannerConfig):
            default = getattr(PlannerConfig, f.name)
            value = node.declare_parameter(
                f.name, list(default) if isinstance(default, tuple) else default
            )
            values[f.name] = tuple(value) if isinstance(default, tuple) else value
        self.sync_timeout_s = float(node.declare_parameter("sync_timeout_s", 5.0))
        # Rebuild seeds and visibility masks in a worker right after each fused frame, so that a
        # request only waits for a rebuild in flight and then plans from the cached masks.
        eager = bool(node.declare_parameter("eager_cache", True))
        self.server = NextBestViewServer(
            PlannerConfig(**values), background=eager, on_refresh=self._on_refresh
        )
        # Perception's output for a frame can trail the camera's pose by seconds (first frames,
        # a feed-forward model on CPU), so parts wait this long for their partners.
        max_age_s = float(node.declare_parameter("sync_max_age_s", 60.0))
        self.sync = StampSync(("depth", "confidence", "pose"), max_age_ns=int(max_age_s * 1e9))
        self.camera_info: OrderedDict[int, np.ndarray] = OrderedDict()
        self.latest_K: np.ndarray | None = None

        self.grid_pub = node.create_publisher(
            "sensor_msgs/msg/PointCloud2", "/area3d/planner/uncertainty_grid", latched=True, depth=1
        )
        self.status_pub = node.create_publisher("std_msgs/msg/String", "/area3d/planner/status")
        self.views_pub = node.create_publisher("nav_msgs/msg/Path", "/area3d/planner/next_views")
        node.create_subscription(
            "sensor_msgs/msg/Image",
            "/area3d/perception/depth",
            lambda m: self._part("depth", m),
            depth=FRAME_QUEUE_DEPTH,
        )
        node.create_subscription(
            "sensor_msgs/msg/Image",
            "/area3d/perception/confidence",
            lambda m: self._part("confidence", m),
            depth=FRAME_QUEUE_DEPTH,
        )
        node.create_subscription(
            "geometry_msgs/msg/PoseStamped",
            "/area3d/camera/pose",
            lambda m: self._part("pose", m),
            depth=FRAME_QUEUE_DEPTH,
        )
        node.create_subscription(
            "sensor_msgs/msg/CameraInfo",
            "/area3d/camera/camera_info",
            self._on_camera_info,
            depth=FRAME_QUEUE_DEPTH,
        )
        node.create_subscription(
            "sensor_msgs/msg/Image",
            "/area3d/semantics/uncertainty",
            self._on_semantic,
            depth=FRAME_QUEUE_DEPTH,
        )
        node.create_service(
            "nav_msgs/srv/GetPlan", "/area3d/planner/next_best_view", self._on_request
        )
        log.info(
            f"planner ready: policy={values['policy']} mode={values['mode']} voxels={self.server.grid.spec.num_voxels}"
        )

    def _on_refresh(self) -> None:
        self.status_pub.publish(msgs.String(data=json.dumps(self.server.status())))

    def _on_camera_info(self, msg) -> None:
        K, _, _ = codecs.camera_info_to_intrinsics(msg)
        self.latest_K = K
        self.camera_info[codecs.stamp_to_ns(msg.header.stamp)] = K
        while len(self.camera_info) > CAMERA_INFO_CACHE:
            self.camera_info.popitem(last=False)

    def _part(self, key: str, msg) -> None:
        stamp = codecs.stamp_to_ns(msg.header.stamp)
        value = codecs.pose_to_matrix(msg.pose) if key == "pose" else codecs.msg_to_image(msg)
        frame = self.sync.add(key, stamp, value)
        for dropped in self.sync.pop_dropped():
            self.node.get_logger().warning(
                f"{dropped.key} at stamp {dropped.stamp_ns} dropped: {dropped.reason}"
            )
        if frame is None:
            return
        K = self.camera_info.get(stamp, self.latest_K)
        if K is None:
            self.node.get_logger().warning(f"frame {stamp}: no camera_info yet, frame dropped")
            return
        self.server.add_frame(stamp, frame["depth"], frame["confidence"], K, frame["pose"])
        self._publish_state(stamp)

    def _on_semantic(self, msg) -> None:
        stamp = codecs.stamp_to_ns(msg.header.stamp)
        if self.server.add_semantic(stamp, codecs.msg_to_image(msg)):
            self._publish_state(stamp)

    def _publish_state(self, stamp_ns: int) -> None:
        self.grid_pub.publish(grid_to_msg(self.server.grid, stamp_ns, "world"))
        self.status_pub.publish(msgs.String(data=json.dumps(self.server.status())))

    def _on_request(self, request):
        log = self.node.get_logger()
        stamp = codecs.stamp_to_ns(request.start.header.stamp)
        try:
            start = codecs.pose_to_matrix(request.start.pose)
        except ValueError as exc:
            log.warning(f"next_best_view: start pose rejected ({exc}); planning without a start")
            start = None
        if not self.server.wait_fused(stamp, self.sync_timeout_s):
            log.warning(
                f"next_best_view: frame {stamp} not fused after {self.sync_timeout_s} s; planning with what is fused"
            )
        poses, reason = self.server.plan(
            PlanRequest(start, stamp, int(round(request.goal.pose.position.x)))
        )
        if reason:
            log.warning(f"next_best_view: {reason}")
        now = self.node.now_ns()
        hdr = codecs.header(now, "world")
        path = msgs.Path(
            header=hdr,
            poses=[
                msgs.PoseStamped(header=codecs.header(now, "world"), pose=codecs.matrix_to_pose(T))
                for T in poses
            ],
        )
        self.views_pub.publish(path)
        self.status_pub.publish(msgs.String(data=json.dumps(self.server.status())))
        return msgs.GetPlan_Response(plan=path)


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(PlannerNode, argv, name="planner")


if __name__ == "__main__":
    raise SystemExit(main())
