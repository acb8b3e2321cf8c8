"""What every message carries: its header (stamp, frame) and, for images and clouds, a byte
payload. Stamps are int nanoseconds since the Unix epoch."""

from __future__ import annotations

from typing import Any

import numpy as np

from area3d_msgs_py import msgs
from area3d_msgs_py.errors import InputError

NS_PER_S = 1_000_000_000


def data_bytes(data: Any) -> np.ndarray:
    """(N,) uint8 view of a message's byte sequence (array.array, bytes or a list of ints)."""
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8).reshape(-1)


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> int nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Any:
    """int nanoseconds (>= 0) -> builtin_interfaces/Time."""
    ns = int(ns)
    if ns < 0:
        raise InputError("stamp_ns", ns, "a non-negative int of nanoseconds")
    sec, nanosec = divmod(ns, NS_PER_S)
    if sec > np.iinfo(np.int32).max:
        raise InputError("stamp_ns", ns, "a time before 2038 (int32 seconds)")
    return msgs.Time(sec=sec, nanosec=nanosec)


def header(stamp_ns: int, frame_id: str) -> Any:
    """std_msgs/Header with the given stamp and frame."""
    if not isinstance(frame_id, str):
        raise InputError("frame_id", frame_id, "a str")
    return msgs.Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)
