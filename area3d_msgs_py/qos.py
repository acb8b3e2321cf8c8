"""The QoS profiles of the graph's topics (all reliable, keep-last)."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

#: ROS 2's default depth for ordinary topics.
DEFAULT_DEPTH = 10
# Frames arrive in bursts (the initial views, 15 at room level); the default depth would drop the
# oldest while a node is busy, and every captured frame matters.
FRAME_DEPTH = 50


def reliable(depth: int = DEFAULT_DEPTH) -> QoSProfile:
    """Reliable, volatile, keep-last ``depth`` (ROS 2's default profile with another depth)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def frames() -> QoSProfile:
    """Per-frame image, pose and camera-info topics."""
    return reliable(FRAME_DEPTH)


def graph_frames(depth: int = FRAME_DEPTH) -> QoSProfile:
    """Per-frame outputs one graph node computes for another (perception -> planner, semantics ->
    planner): transient-local keep-last ``depth``, on both sides. A reader that matches late (a
    node whose discovery is still running when the first frames are processed) still gets them;
    volatile readers (RViz, a recorder) match too."""
    return latched(depth)


def latched(depth: int = 1) -> QoSProfile:
    """Transient-local keep-last: a subscriber that starts late still gets the last ``depth``."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
