"""The camera pose of each captured frame from a robot's TF tree or its odometry, at the frame's
stamp: frames wait (bounded) for the transforms after their stamp, and each one whose pose cannot
be had is dropped with a cause. No ROS here (`pose_inputs.py` wires it to a node).

Three sources, chosen by a node's `pose_source` parameter:
- `topic`: a geometry_msgs/PoseStamped of the optical frame on `area3d/camera/pose` with the
  image's exact stamp (sim_bridge, or a bag): paired by stamp with the images (the nodes'
  `StampSync`), not handled here;
- `tf`: `world_frame` -> the image's `header.frame_id` from /tf and /tf_static, each dynamic edge
  interpolated to the image's stamp (`transforms.TransformBuffer`);
- `odometry`: nav_msgs/Odometry (`header.frame_id` = `world_frame`, `child_frame_id` =
  `body_frame`) at its own rate, interpolated to the image's stamp, composed with the camera's
  fixed mount on the body: given as parameters (body -> the optical frame of the images), or
  looked up in /tf_static (`body_frame` -> the image's frame_id).

A frame whose transforms have not all arrived (the stamp is after the newest sample of an edge, or
a frame is not known yet) waits for them up to `pose_wait_s`, as tf2's message filter does; a
stamp before the history kept, or between two samples of an edge more than `pose_max_interval_s`
apart (an odometry outage: where the camera was is not known), is dropped at once. A dropped frame
is counted by cause (`transforms.LookupFailure.CAUSES`); the first drop of each cause carries
`first` so that a node logs it once. Samples are checked where they enter (`TransformBuffer.add`): a non-unit quaternion,
a jump faster than the speed limits, a stamp ahead of the clock or a second parent is refused with
an `InputError` naming the message field.
"""

from __future__ import annotations

import dataclasses
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.param_fields import described
from area3d_msgs_py.transforms import (
    DEFAULT_MAX_AHEAD_S,
    NS_PER_S,
    ODOMETRY_FIELDS,
    TF_FIELDS,
    Fields,
    LookupFailure,
    TransformBuffer,
)

POSE_SOURCES = ("topic", "tf", "odometry")
MOUNT_SOURCES = ("parameters", "tf_static")
# The camera frame of a mount given as parameters (a ROS frame name has no parentheses).
MOUNTED_CAMERA = "(camera)"
# Frames waiting for their transforms at most (the oldest is dropped beyond).
WAITING_CAPACITY = 64
# lookups that waiting cannot mend: the stamp fell out of the history, or lies in a gap between
# samples already in it
FINAL = (LookupFailure.TOO_OLD, LookupFailure.GAP)


def _xyz(value: tuple) -> str | None:
    return None if len(value) == 3 else "3 numbers [x, y, z] in metres"


def _quaternion(value: tuple) -> str | None:
    if len(value) != 4 or abs(float(np.linalg.norm(value)) - 1.0) > 1e-3:
        return "a unit quaternion [x, y, z, w]"
    return None


@dataclass(frozen=True)
class PoseSourceConfig:
    """Where a node takes the camera pose of each frame from (its parameters)."""

    pose_source: str = described(
        "topic",
        "where each frame's camera pose comes from: topic (PoseStamped of the optical frame on "
        "area3d/camera/pose with the image's stamp), tf (world_frame -> the image's frame_id on "
        "/tf and /tf_static) or odometry (nav_msgs/Odometry on area3d/odom and the camera's "
        "mount), the last two interpolated to the image's stamp",
        choices=POSE_SOURCES,
    )
    pose_tolerance_s: float = described(
        0.0,
        "tf / odometry: a frame stamped up to this long outside the transforms received takes the "
        "nearest one as it is (no extrapolation); 0 = only between two samples, as tf2",
        "seconds",
        (0.0, 60.0),
    )
    pose_wait_s: float = described(
        5.0,
        "tf / odometry: a frame waits this long (node clock) for the transforms after its stamp, "
        "then it is dropped and counted (frames_dropped_no_pose)",
        "seconds",
        (0.0, 3600.0),
    )
    pose_history_s: float = described(
        60.0,
        "tf / odometry: transforms kept per edge, back from its newest (tf2 keeps 10 s; frames "
        "reach the planner after perception, seconds late with a feed-forward model on a CPU)",
        "seconds",
        (0.1, 3600.0),
    )
    pose_max_interval_s: float = described(
        1.0,
        "tf / odometry: a frame stamped between two transforms of an edge further apart than "
        "this is dropped (gap: the transforms paused, an odometry outage, and where the camera "
        "was meanwhile is not known; tf2 interpolates across any gap); raise it for an edge "
        "published more slowly; 0 = no limit",
        "seconds",
        (0.0, 3600.0),
    )
    pose_max_linear_speed: float = described(
        0.0,
        "tf / odometry: a sample moving faster than this from the previous one of its edge is "
        "refused as a jump (0 = not checked: a simulated camera jumps from view to view)",
        "m/s",
        (0.0, 1000.0),
    )
    pose_max_angular_speed: float = described(
        0.0,
        "tf / odometry: the same for rotation (0 = not checked)",
        "rad/s",
        (0.0, 1000.0),
    )
    body_frame: str = described(
        "base_link", "odometry: the child_frame_id of the odometry, the body the camera is on"
    )
    camera_mount: str = described(
        "tf_static",
        "odometry: the camera's fixed mount on the body: from /tf_static (body_frame -> the "
        "image's frame_id) or from mount_translation / mount_rotation",
        choices=MOUNT_SOURCES,
    )
    mount_translation: tuple = described(
        (0.0, 0.0, 0.0),
        "odometry, camera_mount parameters: position [x, y, z] of the images' optical frame in "
        "body_frame",
        "metres",
        check=_xyz,
    )
    mount_rotation: tuple = described(
        (-0.5, 0.5, -0.5, 0.5),
        "odometry, camera_mount parameters: orientation [x, y, z, w] of the images' optical frame "
        "in body_frame (default: looking along the body's x axis, REP 103)",
        check=_quaternion,
    )


def tf_fields(index: int) -> Fields:
    """The fields of the `index`-th transform of a tf2_msgs/TFMessage, named in rejections."""
    prefix = f"transforms[{index}]."
    return Fields(*(prefix + getattr(TF_FIELDS, f.name) for f in dataclasses.fields(Fields)))


class Posed(NamedTuple):
    """A frame whose pose was found: its stamp, what was submitted, T_world_camera (4x4)."""

    stamp_ns: int
    frame: Any
    T: np.ndarray


class Drop(NamedTuple):
    """A frame dropped without a pose: its stamp, the cause (LookupFailure.CAUSES), why, and
    whether it is the first drop of this cause (log it)."""

    stamp_ns: int
    cause: str
    message: str
    first: bool


@dataclass
class _Waiting:
    stamp_ns: int
    frame_id: str
    frame: Any
    since_ns: int
    failure: LookupFailure


class CameraPoses:
    """The camera poses of a node's frames from TF or odometry (`PoseSourceConfig`).

    world_frame: the frame the poses are wanted in. max_ahead_s: a sample's stamp may be at most
    this far ahead of the node's clock. capacity: frames waiting at most.
    Not thread-safe: a node calls it from one callback group.
    """

    def __init__(
        self,
        config: PoseSourceConfig,
        world_frame: str,
        max_ahead_s: float = DEFAULT_MAX_AHEAD_S,
        capacity: int = WAITING_CAPACITY,
    ) -> None:
        if config.pose_source not in ("tf", "odometry"):
            raise InputError("pose_source", config.pose_source, "tf or odometry")
        if not isinstance(world_frame, str) or not world_frame:
            raise InputError("world_frame", world_frame, "the frame the camera poses are in")
        self.config = config
        self.world_frame = world_frame
        self.buffer = TransformBuffer(
            history_s=config.pose_history_s,
            tolerance_s=config.pose_tolerance_s,
            max_linear_speed=config.pose_max_linear_speed or None,
            max_angular_speed=config.pose_max_angular_speed or None,
            max_ahead_s=max_ahead_s,
            max_interval_s=config.pose_max_interval_s,
        )
        self.mounted = config.pose_source == "odometry" and config.camera_mount == "parameters"
        if config.pose_source == "odometry":
            if not config.body_frame:
                raise InputError("body_frame", config.body_frame, "the odometry's child_frame_id")
            if config.body_frame == world_frame:
                raise InputError(
                    "body_frame",
                    config.body_frame,
                    f"a frame other than world_frame {world_frame!r}",
                )
        if self.mounted:  # the mount's values are checked as a sample's are
            self.buffer.add(
                config.body_frame,
                MOUNTED_CAMERA,
                0,
                config.mount_translation,
                config.mount_rotation,
                static=True,
                fields=Fields(translation="mount_translation", rotation="mount_rotation"),
            )
        self.wait_ns = int(config.pose_wait_s * NS_PER_S)
        self.capacity = int(capacity)
        self._waiting: deque[_Waiting] = deque()
        self.dropped: Counter[str] = Counter()
        self._drops: list[Drop] = []

    # samples -------------------------------------------------------------------------------------
    def add_transform(
        self,
        parent: str,
        child: str,
        stamp_ns: int,
        translation: Any,
        rotation: Any,
        *,
        static: bool,
        now_ns: int,
        fields: Fields = TF_FIELDS,
    ) -> bool:
        """One edge of /tf (or /tf_static: `static`); see TransformBuffer.add. With the odometry
        source only static edges are taken (the mount); a dynamic one is ignored (False)."""
        if self.config.pose_source == "odometry" and not static:
            return False
        return self.buffer.add(
            parent, child, stamp_ns, translation, rotation, static=static, now_ns=now_ns,
            fields=fields,
        )  # fmt: skip

    def add_odometry(
        self,
        frame_id: str,
        child_frame_id: str,
        stamp_ns: int,
        position: Any,
        orientation: Any,
        now_ns: int,
    ) -> bool:
        """One nav_msgs/Odometry pose of body_frame in world_frame; InputError naming the field of
        a frame other than those, or of a sample TransformBuffer.add refuses."""
        if frame_id != self.world_frame:
            raise InputError(
                ODOMETRY_FIELDS.parent, frame_id, f"{self.world_frame!r} (world_frame)"
            )
        if child_frame_id != self.config.body_frame:
            raise InputError(
                ODOMETRY_FIELDS.child, child_frame_id, f"{self.config.body_frame!r} (body_frame)"
            )
        return self.buffer.add(
            frame_id, child_frame_id, stamp_ns, position, orientation, now_ns=now_ns,
            fields=ODOMETRY_FIELDS,
        )  # fmt: skip

    # frames --------------------------------------------------------------------------------------
    def _lookup(self, stamp_ns: int, frame_id: str) -> np.ndarray:
        camera = MOUNTED_CAMERA if self.mounted else frame_id
        return self.buffer.lookup(self.world_frame, camera, stamp_ns)

    def submit(self, stamp_ns: int, frame_id: str, frame: Any, now_ns: int) -> list[Posed]:
        """A whole frame (its images) at `stamp_ns` in `frame_id`: posed now, or held until its
        transforms arrive (`release`). Returns the frames posed by this call."""
        try:
            return [Posed(int(stamp_ns), frame, self._lookup(stamp_ns, frame_id))]
        except LookupFailure as failure:
            if failure.cause in FINAL:
                self._drop(int(stamp_ns), failure)
                return []
            self._waiting.append(_Waiting(int(stamp_ns), frame_id, frame, int(now_ns), failure))
        while len(self._waiting) > self.capacity:
            old = self._waiting.popleft()
            self._drop(
                old.stamp_ns,
                old.failure,
                f"more than {self.capacity} frames wait for their transforms",
            )
        return []

    def release(self, now_ns: int) -> list[Posed]:
        """The waiting frames whose transforms have arrived; those waiting longer than
        pose_wait_s, or whose stamp fell out of the history, are dropped."""
        posed = []
        still = deque()
        for waiting in self._waiting:
            try:
                posed.append(
                    Posed(
                        waiting.stamp_ns,
                        waiting.frame,
                        self._lookup(waiting.stamp_ns, waiting.frame_id),
                    )
                )
                continue
            except LookupFailure as failure:
                waiting.failure = failure
            if waiting.failure.cause in FINAL:
                self._drop(waiting.stamp_ns, waiting.failure)
            elif now_ns - waiting.since_ns > self.wait_ns:
                self._drop(
                    waiting.stamp_ns,
                    waiting.failure,
                    f"not found within pose_wait_s {self.wait_ns / NS_PER_S:g} s",
                )
            else:
                still.append(waiting)
        self._waiting = still
        return posed

    def forget_frames(self) -> int:
        """Forget the frames waiting for their transforms (the transforms stay); how many."""
        waiting = len(self._waiting)
        self._waiting.clear()
        return waiting

    def _drop(self, stamp_ns: int, failure: LookupFailure, why: str = "") -> None:
        first = failure.cause not in self.dropped
        self.dropped[failure.cause] += 1
        message = f"frame at stamp {stamp_ns} dropped, no camera pose ({failure.cause}): {failure}"
        self._drops.append(
            Drop(stamp_ns, failure.cause, f"{message}; {why}" if why else message, first)
        )

    def pop_drops(self) -> list[Drop]:
        """The frames dropped since the last call, oldest first."""
        drops, self._drops = self._drops, []
        return drops

    def __len__(self) -> int:
        """Frames waiting for their transforms."""
        return len(self._waiting)

    def status(self) -> dict:
        """{frames_waiting_for_pose, frames_dropped_no_pose: {cause: count}} (JSON-ready)."""
        return {
            "frames_waiting_for_pose": len(self._waiting),
            "frames_dropped_no_pose": dict(self.dropped),
        }
