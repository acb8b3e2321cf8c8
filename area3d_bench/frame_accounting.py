"""What a node's status says it did with the frames it was sent: passed on (published, fused) or
dropped and counted, each drop said in its log. A frame that neither count holds was lost on the
way, unnoticed: the soak benchmark (`soak.py`) asks that every frame sent be accounted for."""

from __future__ import annotations

# the frames each node drops and counts (each said in its log): its status's names; the pose
# source's drops (with TF or odometry) are counted by cause
PERCEPTION_DROPS = (
    "frames_dropped_backlog",
    "frames_dropped_without_camera_info",
    "frames_dropped_backend_failure",
    "frames_dropped_no_pose",
)
PLANNER_DROPS = ("frames_dropped_backlog", "frames_dropped_no_pose")


def dropped(status: dict, names: tuple[str, ...]) -> int:
    """The frames one status line counts as dropped under `names` (a count or {cause: count})."""
    counts = [status.get(name) or 0 for name in names]
    return sum(sum(c.values()) if isinstance(c, dict) else c for c in counts)


def perception_accounted(status: dict) -> int:
    """Frames perception published or dropped and counted, from one of its status lines."""
    return status.get("frames_published", 0) + dropped(status, PERCEPTION_DROPS)


def planner_accounted(status: dict) -> int:
    """Frames the planner fused or dropped and counted, from one of its status lines."""
    return status.get("frames_fused", 0) + dropped(status, PLANNER_DROPS)
