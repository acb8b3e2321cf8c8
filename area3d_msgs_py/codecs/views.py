"""The next-best-view service (area3d_interfaces/srv/NextBestView): requests and answers <->
numpy (views are (N, 4, 4) optical-frame poses, best first)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from area3d_msgs_py import msgs
from area3d_msgs_py.codecs.header import header, stamp_to_ns
from area3d_msgs_py.codecs.poses import (
    matrices_to_pose_array,
    matrix_to_pose,
    pose_array_to_matrices,
    pose_to_matrix,
)
from area3d_msgs_py.errors import InputError

#: Planning modes a request may name; "" leaves the planner's own `mode` parameter.
VIEW_MODES = ("closed_loop", "batch")
UINT32_MAX = 2**32 - 1


class ViewRequest(NamedTuple):
    """A NextBestView request: how many views, the mode ("" = the planner's), the camera's
    current pose (4x4 in frame_id), the stamp of the last frame it was captured with, and the
    caller's id for the request (0 = none; a resend carries the id of the request it repeats)."""

    count: int
    mode: str
    current: np.ndarray
    stamp_ns: int
    frame_id: str
    request_id: int = 0


class ViewAnswer(NamedTuple):
    """A NextBestView response: views (N, 4, 4) optical-frame poses in frame_id, best first, and
    the predicted gain of each (N,); success False with a message and no views when refused."""

    success: bool
    message: str
    views: np.ndarray
    gains: np.ndarray
    stamp_ns: int
    frame_id: str


def _check_mode(mode: Any) -> str:
    if mode not in ("", *VIEW_MODES):
        raise InputError("mode", mode, f"one of {', '.join(VIEW_MODES)} or empty")
    return mode


def view_request_to_msg(
    count: int,
    current: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    mode: str = "",
    request_id: int = 0,
) -> Any:
    """area3d_interfaces/srv/NextBestView.Request. count: views wanted, 0 = one in closed loop,
    the rest of the budget in batch; current: 4x4 camera pose in frame_id, stamped with the last
    captured frame; request_id: the caller's id for it (0 = none), which a resend of it keeps."""
    expected = "an int of views >= 0 (0 = one in closed_loop, the rest of the budget in batch)"
    if not isinstance(count, int | np.integer) or isinstance(count, bool):
        raise InputError("count", count, expected)
    if not 0 <= count <= UINT32_MAX:
        raise InputError("count", count, expected)
    if (
        not isinstance(request_id, int | np.integer)
        or isinstance(request_id, bool)
        or not 0 <= request_id < 2**64
    ):
        raise InputError("request_id", request_id, "an int in [0, 2^64) (0 = none)")
    pose = matrix_to_pose(current, "current")
    return msgs.NextBestView.Request(
        count=int(count),
        mode=_check_mode(mode),
        current=msgs.PoseStamped(header=header(stamp_ns, frame_id), pose=pose),
        request_id=int(request_id),
    )


def msg_to_view_request(msg: Any) -> ViewRequest:
    """Checked fields of a NextBestView request (mode, current pose); see ViewRequest."""
    return ViewRequest(
        count=int(msg.count),
        mode=_check_mode(msg.mode),
        current=pose_to_matrix(msg.current.pose, "current.pose"),
        stamp_ns=stamp_to_ns(msg.current.header.stamp),
        frame_id=msg.current.header.frame_id,
        request_id=int(msg.request_id),
    )


def view_answer_to_msg(
    views: np.ndarray, gains: np.ndarray, stamp_ns: int, frame_id: str, message: str = ""
) -> Any:
    """A successful NextBestView.Response: views (N, 4, 4) best first, gains (N,) finite;
    `message` what the caller should know about them ("" when nothing: the map held the request's
    frame and no view repeats one handed out before)."""
    views = np.asarray(views, dtype=np.float64)
    gains = np.asarray(gains, dtype=np.float32).reshape(-1)
    pose_array = matrices_to_pose_array(views, stamp_ns, frame_id)
    if gains.shape != (len(views),):
        raise InputError("gains", gains.shape, f"({len(views)},): one gain per view")
    if not np.isfinite(gains).all():
        raise InputError("gains", gains.tolist(), "finite predicted gains")
    return msgs.NextBestView.Response(
        success=True, message=str(message), views=pose_array, gains=gains
    )


def view_refusal_to_msg(message: str, stamp_ns: int, frame_id: str) -> Any:
    """A NextBestView.Response that says why no view is given (success False, no views)."""
    if not isinstance(message, str) or not message:
        raise InputError("message", message, "the reason no view is given")
    return msgs.NextBestView.Response(
        success=False,
        message=message,
        views=msgs.PoseArray(header=header(stamp_ns, frame_id), poses=[]),
        gains=np.zeros(0, np.float32),
    )


def msg_to_view_answer(msg: Any) -> ViewAnswer:
    """Checked fields of a NextBestView response; see ViewAnswer."""
    views = pose_array_to_matrices(msg.views, "views.poses")
    gains = np.array(msg.gains, dtype=np.float32)
    if gains.shape != (len(views),):
        raise InputError("gains", gains.shape, f"({len(views)},): one gain per view")
    return ViewAnswer(
        success=bool(msg.success),
        message=msg.message,
        views=views,
        gains=gains,
        stamp_ns=stamp_to_ns(msg.views.header.stamp),
        frame_id=msg.views.header.frame_id,
    )
