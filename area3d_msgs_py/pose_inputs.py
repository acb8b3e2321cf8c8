"""A node's camera poses from TF or odometry: the subscriptions of `pose_source.CameraPoses`.

With `pose_source: tf` the node reads /tf and /tf_static; with `odometry` the odometry topic and,
for the camera's mount, /tf_static. Each sample goes into the core (a refused one is logged with
its field and counted in the node's `Rejections`, the other transforms of its message are kept),
and after each, and on a timer, the frames waiting for their transforms are tried again. The
first frame dropped for each cause is logged; every drop is counted in the node's status
(`frames_dropped_no_pose`, by cause).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from area3d_msgs_py import codecs, topics
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.guard import Rejections, reject, subscribe
from area3d_msgs_py.pose_source import CameraPoses, Posed, PoseSourceConfig, tf_fields

# How often the frames waiting for their transforms are checked against pose_wait_s, seconds.
WAIT_CHECK_S = 0.1


class PoseInputs:
    """Subscribes what `config.pose_source` needs on `node` and calls `on_posed(stamp_ns, frame,
    T_world_camera)` for each submitted frame whose pose is found; `on_change()` after a frame
    was dropped (the node's status)."""

    def __init__(
        self,
        node: Any,
        config: PoseSourceConfig,
        world_frame: str,
        max_ahead_s: float,
        camera_qos: str,
        rejections: Rejections,
        on_posed: Callable[[int, Any, np.ndarray], None],
        on_change: Callable[[], None] | None = None,
        callback_group: Any = None,
    ) -> None:
        self.node = node
        self.core = CameraPoses(config, world_frame, max_ahead_s)
        self.rejections = rejections
        self.on_posed = on_posed
        self.on_change = on_change
        inputs: list[tuple[topics.Topic, Callable, Any]] = []
        if config.pose_source == "tf":
            inputs.append((topics.TF, lambda m: self._on_tf(m, static=False), topics.TF.qos()))
        else:
            odometry = topics.ODOMETRY
            inputs.append((odometry, self._on_odometry, odometry.reader_qos(camera_qos)))
        if config.pose_source == "tf" or config.camera_mount == "tf_static":
            static = topics.TF_STATIC
            inputs.append((static, lambda m: self._on_tf(m, static=True), static.qos()))
        for topic, callback, profile in inputs:
            subscribe(
                node, topic.msg_type, topic.name, callback, profile, rejections,
                callback_group=callback_group,
            )  # fmt: skip
        node.create_timer(WAIT_CHECK_S, self.release, callback_group=callback_group)

    def _now_ns(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def submit(self, stamp_ns: int, frame_id: str, frame: Any) -> None:
        """A whole frame in `frame_id` (its images' header.frame_id), posed now or later."""
        self._deliver(self.core.submit(stamp_ns, frame_id, frame, self._now_ns()))

    def release(self) -> None:
        """Pose the waiting frames whose transforms have arrived; drop those waiting too long."""
        self._deliver(self.core.release(self._now_ns()))

    def forget_frames(self) -> int:
        """Forget the frames waiting for their camera pose; how many."""
        return self.core.forget_frames()

    def status(self) -> dict:
        return self.core.status()

    def _on_tf(self, msg: Any, static: bool) -> None:
        topic = (topics.TF_STATIC if static else topics.TF).name
        now = self._now_ns()
        for i, edge in enumerate(msg.transforms):
            stamp = codecs.stamp_to_ns(edge.header.stamp)
            t, q = edge.transform.translation, edge.transform.rotation
            try:
                self.core.add_transform(
                    edge.header.frame_id, edge.child_frame_id, stamp, (t.x, t.y, t.z),
                    (q.x, q.y, q.z, q.w), static=static, now_ns=now, fields=tf_fields(i),
                )  # fmt: skip
            except InputError as exc:  # this transform only: the others of the message count
                reject(self.node, self.rejections, f"{topic} at stamp {stamp}", exc, topic=topic)
        self.release()

    def _on_odometry(self, msg: Any) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        self.core.add_odometry(
            msg.header.frame_id, msg.child_frame_id, codecs.stamp_to_ns(msg.header.stamp),
            (p.x, p.y, p.z), (q.x, q.y, q.z, q.w), self._now_ns(),
        )  # fmt: skip
        self.release()

    def _deliver(self, posed: list[Posed]) -> None:
        drops = self.core.pop_drops()
        for drop in drops:
            if drop.first:  # once per cause; the status counts every one
                self.node.get_logger().warning(
                    f"{drop.message} (further frames dropped for {drop.cause!r} are counted in "
                    "the status, frames_dropped_no_pose, not logged)"
                )
        if drops and self.on_change is not None:
            self.on_change()
        for frame in posed:
            self.on_posed(frame.stamp_ns, frame.frame, frame.T)
