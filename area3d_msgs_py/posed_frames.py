"""Whole, posed frames of a node that reads perception's outputs: the planner's and the
reconstruction's inputs, wired once.

The parts a node names (perception's depth and confidence, the camera's colour, ...) pair by stamp
(`frame_sync.StampSync`); the camera pose is one more part (the pose topic) or comes from TF or
odometry at the frame's stamp (`pose_inputs.PoseInputs`); the keyframe rule of a streaming camera
chooses which frames go on (`keyframes.KeyframeSelector`: the others are counted as skipped); a
frame then waits for the camera info of its stamp (`frame_sync.CameraInfoCache`, `HeldFrames`)
and goes to the node's `deliver(stamp, frame, K)` with `frame["pose"]` set. A part that expires
unpaired is logged (throttled) and counted. Callbacks run in the node's `callback_group`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import fields
from typing import Any

import numpy as np

from area3d_msgs_py import codecs, topics
from area3d_msgs_py.frame_sync import CameraInfoCache, HeldFrames, StampSync, pairing_warning
from area3d_msgs_py.guard import Rejections, subscribe
from area3d_msgs_py.inputs import check_frame_id, check_stamp, decode_camera_info
from area3d_msgs_py.keyframes import KeyframeConfig, KeyframeSelector
from area3d_msgs_py.pose_inputs import PoseInputs
from area3d_msgs_py.pose_source import PoseSourceConfig

CAMERA_INFO_CACHE = 64
# The camera's small per-frame messages (poses, camera info) run ahead of perception's images,
# which trail by the perception backlog: a minute of them at 30 Hz may wait (they are small), and
# a reader queue that overflows loses the frame for good.
POSES_PENDING = 2048
# Complete frames held while no camera info has arrived yet (oldest dropped beyond this).
MAX_FRAMES_WITHOUT_INFO = 64


class PosedFrames:
    """Subscribes `parts` ({key: (topic, decode(msg) -> value)}), the camera info and the pose of
    the node's `pose_source` on `node`, and calls `deliver(stamp_ns, frame, K)` with each whole
    keyframe ({key: value, "pose": T_world_cam}); `on_change()` when a count changed (the node's
    status). `p`: the node's parameter values (the keyframe and pose-source fields, sync_slop_s,
    sync_max_age_s, world_frame, max_stamp_ahead_s, camera_qos); `pending_caps`: parts that may
    run ahead in numbers ({key: count}, the pose's always)."""

    def __init__(
        self,
        node: Any,
        parts: dict[str, tuple[topics.Topic, Callable[[Any], Any]]],
        p: dict,
        rejections: Rejections,
        deliver: Callable[[int, dict, np.ndarray], None],
        on_change: Callable[[], None],
        callback_group: Any = None,
        pending_caps: dict[str, int] | None = None,
    ) -> None:
        self.node, self.deliver, self.on_change = node, deliver, on_change
        self.world_frame = p["world_frame"]
        self.max_stamp_ahead_s = p["max_stamp_ahead_s"]
        pose_config = PoseSourceConfig(**{f.name: p[f.name] for f in fields(PoseSourceConfig)})
        self.pose_source = pose_config.pose_source
        pose_topic = self.pose_source == "topic"  # else TF or odometry (self.poses)
        self.decoders = {key: decode for key, (_, decode) in parts.items()}
        if pose_topic:
            self.decoders["pose"] = self._decode_pose
        self.sync = StampSync(
            tuple(self.decoders),
            max_age_ns=int(p["sync_max_age_s"] * 1e9),
            pending_caps={"pose": POSES_PENDING, **(pending_caps or {})},
            slop_ns=int(round(p["sync_slop_s"] * 1e9)),
        )
        self.keyframe_config = KeyframeConfig(**{f.name: p[f.name] for f in fields(KeyframeConfig)})
        self.keyframes = KeyframeSelector(self.keyframe_config)
        self.camera_info = CameraInfoCache(CAMERA_INFO_CACHE)
        self.waiting = HeldFrames(MAX_FRAMES_WITHOUT_INFO)
        self.dropped = 0  # parts dropped unpaired
        self.poses = None
        if not pose_topic:
            self.poses = PoseInputs(
                node, pose_config, self.world_frame, self.max_stamp_ahead_s, p["camera_qos"],
                rejections, self._posed, on_change, callback_group=callback_group,
            )  # fmt: skip
        inputs = [
            (topic, lambda m, key=key: self._part(key, m), None)
            for key, (topic, _) in parts.items()
        ]
        inputs.append((topics.CAMERA_INFO, self._on_camera_info, POSES_PENDING))
        if pose_topic:
            inputs.append((topics.POSE, lambda m: self._part("pose", m), POSES_PENDING))
        for topic, callback, depth in inputs:
            subscribe(
                node, topic.msg_type, topic.name, callback,
                topic.reader_qos(p["camera_qos"], depth), rejections,
                callback_group=callback_group,
            )  # fmt: skip

    @property
    def near(self) -> Callable | None:
        """The keyframe rule's "taken near" test (None when every frame is taken)."""
        return None if self.keyframe_config.every_frame else self.keyframe_config.near

    def stamp(self, msg: Any) -> int:
        """The message's stamp, checked against the node's clock."""
        now = self.node.get_clock().now().nanoseconds
        return check_stamp(msg, now, self.max_stamp_ahead_s)

    def _decode_pose(self, msg: Any) -> np.ndarray:
        check_frame_id(msg, self.world_frame)
        return codecs.pose_to_matrix(msg.pose)

    def _part(self, key: str, msg: Any) -> None:
        stamp = self.stamp(msg)
        paired = self.sync.add_part(key, stamp, self.decoders[key](msg))
        for dropped in self.sync.pop_dropped():
            self.dropped += 1
            self.node.get_logger().warning(
                f"{dropped.key} at stamp {dropped.stamp_ns} dropped: {dropped.reason}",
                throttle_duration_sec=1.0,
            )
        if paired is None:
            return
        stamp, frame = paired
        if self.poses is not None:  # the pose at the frame's stamp, now or once it has arrived
            self.poses.submit(stamp, msg.header.frame_id, frame)
            return
        self._keyframe(stamp, frame)

    def _posed(self, stamp: int, frame: dict, T_world_cam: np.ndarray) -> None:
        self._keyframe(stamp, {**frame, "pose": T_world_cam})

    def _keyframe(self, stamp: int, frame: dict) -> None:
        if not self.keyframes.offer(stamp, frame["pose"]):
            self.on_change()
            return  # the camera has not moved, turned or waited enough: skipped, counted
        K = self.camera_info.get(stamp)
        if K is None:
            warning = self.waiting.hold(stamp, frame, topics.CAMERA_INFO.name)
            if warning:
                self.node.get_logger().warning(warning)
            return
        self.deliver(stamp, frame, K)

    def _on_camera_info(self, msg: Any) -> None:
        stamp = self.stamp(msg)
        K, _, _ = decode_camera_info(msg)
        self.camera_info.add(stamp, K)
        for held_stamp, frame in self.waiting.release():
            self.deliver(held_stamp, frame, self.camera_info.get(held_stamp))

    def clear(self) -> tuple[int, int]:
        """Forget what waits (a reset, a map loaded): (parts waiting for partners, frames waiting
        for camera info or a pose); the next frame is a keyframe. Camera info and transforms stay:
        they describe the robot, not the map."""
        self.keyframes.reset()
        parts = self.sync.clear()
        held = len(self.waiting.release())
        held += 0 if self.poses is None else self.poses.forget_frames()
        return parts, held

    def status(self, min_pairing_rate: float | None = None) -> dict:
        """The counts for the node's status: keyframes, pairing, drops, the pose source's."""
        warning = None if min_pairing_rate is None else pairing_warning(self.sync, min_pairing_rate)
        return {
            **self.keyframes.status(),
            "frames_paired": self.sync.frames_paired,
            "pairing_rate": self.sync.pairing_rate(),
            "warnings": [warning] if warning else [],
            "parts_dropped_unpaired": self.dropped,
            "frames_dropped_without_camera_info": self.waiting.dropped,
            **({} if self.poses is None else self.poses.status()),
        }
