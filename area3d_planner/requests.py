"""A next-best-view request and its answer, and the checks and notes that need no map lock:
what a request asks (`PlanRequest`), what it gets (`Plan`), a request checked and counted before
its masks are waited for (`PlanTicket`), the reason a request gets no plan (`check_request`) and
what to say of a view handed out before (`repeats_note`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_planner.config import MODES
from area3d_planner.greedy import poses_alike


@dataclass
class PlanRequest:
    """A next-best-view request: current camera pose, the stamp of the last captured frame
    (0 = do not wait), how many views (0 = all that the remaining budget allows in batch mode,
    one in closed loop), the mode ("" = the planner's `mode`) and the caller's id for the
    request (0 = none: `scheduler.ANSWERS_KEPT`); `count_field` and `stamp_field` name how many
    views and the frame's stamp in the caller's message (NextBestView's `count` and
    `current.header.stamp`, GetPlan's `goal.pose.position.x` and `start.header.stamp`)."""

    start: np.ndarray | None
    stamp_ns: int = 0
    num_views: int = 0
    mode: str = ""
    request_id: int = 0
    count_field: str = "count"
    stamp_field: str = "current.header.stamp"


def get_plan_request(start: np.ndarray | None, stamp_ns: int, x: float) -> PlanRequest:
    """nav_msgs/GetPlan's request, how many views in `goal.pose.position.x`; InputError unless
    that is a whole number >= 0 (NaN, 2.7, -1)."""
    if not (np.isfinite(x) and x == round(x) and x >= 0):
        raise InputError("goal.pose.position.x", x, "a whole number of views >= 0")
    return PlanRequest(
        start,
        stamp_ns,
        int(x),
        count_field="goal.pose.position.x",
        stamp_field="start.header.stamp",
    )


def check_request_stamp(request: PlanRequest, now_ns: int, max_ahead_s: float) -> None:
    """InputError when a request's frame stamp (0 = do not wait) is more than `max_ahead_s`
    ahead of the planner's clock: no frame of it can be fused, and the request would wait its
    whole `sync_timeout_s` (a caller's clock ahead, or a stamp in the wrong units)."""
    if request.stamp_ns > now_ns + int(max_ahead_s * 1e9):
        raise InputError(
            request.stamp_field,
            request.stamp_ns,
            f"0 (do not wait) or a frame stamp at most {max_ahead_s:g} s ahead of the planner's "
            f"clock ({now_ns} ns)",
        )


class Plan(NamedTuple):
    """A request's answer: poses (T_world_cam, optical frame) best first, the predicted gain of
    each (`SelectedViews`), the reason when there are none ("" when all is well), and with views
    what the caller should know about them (`note`: a view handed out before, the map lacking
    the request's frame; "" when nothing)."""

    poses: list
    gains: list
    reason: str
    note: str = ""


@dataclass
class PlanTicket:
    """A request checked and counted (`begin_plan`), before its masks are waited for: what it
    wants, and the map versions whose masks it plans from."""

    request: PlanRequest
    want: int
    remaining: int
    closed_loop: bool
    target: int  # the map version that holds the request's frame
    pipelines: bool  # planned from the masks of the previous request's frame (`pipeline_masks`)
    base: int  # that frame's map version when those masks are to be waited for (0: none)
    started: float  # time.perf_counter() when the request was checked


def repeats_note(poses: list, answered: list, fused: list, radius: float, angle_deg: float) -> str:
    """What to say of views that repeat one handed out before (`answered`: (pose, request stamp)
    of each, in order), within `radius` metres and `angle_deg` of it: which, and whether a frame
    from there was fused since (`fused`: (stamp, pose) of each fused frame). "" when none
    repeats."""
    notes = []
    answered_poses = [U for U, _ in answered]
    fused_poses = [F for _, F in fused]
    for i, T in enumerate(poses):
        repeated = np.flatnonzero(poses_alike(answered_poses, T, radius, angle_deg))
        if repeated.size == 0:
            continue
        j = int(repeated[0])  # the first view handed out from there
        U, stamp = answered[j]
        from_there = poses_alike(fused_poses, U, radius, angle_deg)
        since = [s for (s, _), near in zip(fused, from_there, strict=True) if near and s > stamp]
        seen = (
            f"a frame from there was fused (stamp {since[-1]}) and it still sees the most "
            "uncertainty"
            if since
            else "no frame from there has been fused since"
        )
        notes.append(f"view {i} was handed out before (view {j} of this map): {seen}")
    return "; ".join(notes)


def check_request(
    request: PlanRequest, frames: int, default_mode: str, remaining: int, spent: str, sums: dict
) -> tuple[int, int] | str:
    """(views wanted, remaining budget) for a request, or the reason it gets no plan: `frames`
    fused so far, the planner's `default_mode`, the `remaining` budget and what to say when it
    is `spent`, the evidence `sums` by name (NaN voxels make them non-finite)."""
    if frames == 0:
        return "no frame fused yet: capture the initial views first"
    if request.start is not None:
        s = np.asarray(request.start, float)
        if s.shape != (4, 4) or not np.all(np.isfinite(s)):
            return f"start: got {s.shape} with non-finite values, expected a finite (4, 4) pose"
    try:
        num = int(request.num_views)
    except (TypeError, ValueError):
        return f"{request.count_field}: got {request.num_views!r}, expected an integer >= 0"
    if num < 0:
        return (
            f"{request.count_field}: got {num}, expected an integer >= 0 (0 = the remaining budget)"
        )
    mode = request.mode or default_mode
    if mode not in MODES:
        return f"mode: got {mode!r}, expected one of {', '.join(MODES)} (empty: the planner's)"
    if remaining == 0:
        return spent
    # 0: batch plans the whole remaining budget at once, closed loop the next best view only
    want = num or (remaining if mode == "batch" else 1)
    if want > remaining:
        return (
            f"{request.count_field}: got {num}, expected at most the remaining budget {remaining}"
        )
    for name, arr in sums.items():
        # a float64 sum of float32 values cannot overflow: it is finite iff every value is
        if not np.isfinite(arr.sum(dtype=np.float64)):
            return f"{name} uncertainty: got NaN voxels, expected finite values"
    return want, remaining
