"""Which frames of a streaming camera to integrate: the keyframe rule of mapping stacks.

A camera driver streams at 15-30 Hz while the robot moves; integrating every frame costs a core
and adds little (consecutive frames see the same surface from almost the same place). A frame is
integrated when the camera moved `keyframe_distance` metres or turned `keyframe_angle_deg`
degrees since the last integrated frame, or `keyframe_interval_s` seconds of stamp time passed
(a camera at rest still refreshes the map); every other frame is skipped and counted. Each
threshold set to 0 is off; all three 0: every frame is integrated (a triggered camera that sends
one frame per planned view). Time is the frames' stamps, so recorded runs replay alike at any
speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from area3d_msgs_py.param_fields import described


@dataclass(frozen=True)
class KeyframeConfig:
    """When a frame is integrated (node parameters of perception and the planner)."""

    keyframe_distance: float = described(
        0.1,
        "a frame is integrated once the camera moved this far since the last integrated one "
        "(0 = off; all three 0: every frame)",
        "metres",
        (0.0, 100.0),
    )
    keyframe_angle_deg: float = described(
        10.0,
        "... or turned this far",
        "degrees",
        (0.0, 180.0),
    )
    keyframe_interval_s: float = described(
        1.0,
        "... or this much stamp time passed",
        "seconds",
        (0.0, 3600.0),
    )

    @property
    def every_frame(self) -> bool:
        return not (self.keyframe_distance or self.keyframe_angle_deg or self.keyframe_interval_s)

    def near(self, T_a: np.ndarray, T_b: np.ndarray) -> bool:
        """Two camera poses are within the thresholds of each other (the same keyframe's
        place); with the distance and angle off only identical poses are."""
        dist, angle = pose_difference(T_a, T_b)
        if not (self.keyframe_distance or self.keyframe_angle_deg):
            return dist == 0.0 and angle == 0.0
        return (not self.keyframe_distance or dist < self.keyframe_distance) and (
            not self.keyframe_angle_deg or angle < self.keyframe_angle_deg
        )


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(distance in metres, rotation angle in degrees) between two (4, 4) poses."""
    T_a, T_b = np.asarray(T_a, float), np.asarray(T_b, float)
    dist = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
    cos = (np.trace(T_a[:3, :3].T @ T_b[:3, :3]) - 1.0) / 2.0
    return dist, math.degrees(math.acos(min(1.0, max(-1.0, cos))))


class KeyframeSelector:
    """Decides frame by frame, in arrival order, which to integrate; counts both kinds."""

    def __init__(self, config: KeyframeConfig) -> None:
        self.config = config
        self.integrated = 0
        self.skipped = 0
        self._last: tuple[int, np.ndarray] | None = None  # (stamp, pose) of the last keyframe

    def offer(self, stamp_ns: int, T_world_cam: np.ndarray) -> bool:
        """True: integrate this frame (it becomes the last keyframe); False: skip it."""
        c = self.config
        keep = c.every_frame or self._last is None
        if not keep:
            last_stamp, last_pose = self._last
            dist, angle = pose_difference(last_pose, T_world_cam)
            keep = (
                (c.keyframe_distance > 0 and dist >= c.keyframe_distance)
                or (c.keyframe_angle_deg > 0 and angle >= c.keyframe_angle_deg)
                or (
                    c.keyframe_interval_s > 0
                    and abs(stamp_ns - last_stamp) >= c.keyframe_interval_s * 1e9
                )
            )
        if keep:
            self._last = (int(stamp_ns), np.array(T_world_cam, float))
            self.integrated += 1
        else:
            self.skipped += 1
        return keep

    def reset(self) -> None:
        """Forget the last keyframe (the next frame is integrated); the counts stay."""
        self._last = None

    def status(self) -> dict:
        return {"frames_integrated": self.integrated, "frames_skipped": self.skipped}
