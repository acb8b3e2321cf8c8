"""Exact-stamp pairing of the messages that make up one captured frame (color, depth, pose).

Every message of a frame carries the capture stamp of its source frame, so a frame is complete when
each stream has delivered a message with the same `stamp_ns`. Entries wait in one small dict per
stream; when a frame completes, the parts still waiting with stamps more than `max_age_ns` before
it are dropped and reported, so a pose whose images never arrive (or the reverse) cannot pile up.
Age is measured on the stamps, not on the wall clock, so recorded episodes replay the same way at
any speed.

Why against the frame that completes, and not the newest stamp seen: each stream delivers its
parts in order, so once a frame is complete every stream has delivered what was published before
it, and a part waiting that far behind it will never find its partners. The newest stamp *seen*
says no such thing: one part of a later frame overtaking the rest of an earlier frame (frames
replayed faster than captured, saved stamps minutes apart, the history a restarted node gets from
transient-local topics all at once) or one stamp from the future would push every waiting part
out. And an old frame replayed after newer ones completed (a node brought up to date after a
restart) pairs like any other: only frames completing after its parts arrived can expire them.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from area3d_msgs_py.errors import InputError

# Keep unmatched parts for 5 s of stamp time (our choice: well above one render + transport).
MAX_AGE_NS = 5_000_000_000
# Hard cap on waiting entries per stream, whatever their age (a stuck stream must not grow memory).
MAX_PENDING = 64


@dataclass(frozen=True)
class Dropped:
    """A part that was discarded without a partner: its stream, its stamp and why."""

    key: str
    stamp_ns: int
    reason: str


class StampSync:
    """Pairs messages of several streams by identical stamp.

    keys: the stream names that make a complete frame, e.g. ("color", "depth", "pose").
    max_pending: the cap on waiting parts per stream; `pending_caps` overrides it per stream (a
    pose is 128 bytes and may wait in thousands for images that trail it).
    """

    def __init__(
        self,
        keys: Sequence[str],
        max_age_ns: int = MAX_AGE_NS,
        max_pending: int = MAX_PENDING,
        pending_caps: dict[str, int] | None = None,
    ) -> None:
        if len(keys) == 0 or len(set(keys)) != len(keys):
            raise InputError("keys", list(keys), "one or more distinct stream names")
        if max_age_ns < 0:
            raise InputError("max_age_ns", max_age_ns, "a duration >= 0 nanoseconds")
        if max_pending < 1:
            raise InputError("max_pending", max_pending, "an integer >= 1")
        self.keys = tuple(keys)
        self.max_age_ns = int(max_age_ns)
        self.max_pending = int(max_pending)
        self._caps = {k: int((pending_caps or {}).get(k, max_pending)) for k in self.keys}
        if min(self._caps.values()) < 1:
            raise InputError("pending_caps", pending_caps, "integers >= 1")
        self._pending: dict[str, dict[int, Any]] = {k: {} for k in self.keys}
        self._dropped: list[Dropped] = []

    def add(self, key: str, stamp_ns: int, value: Any) -> dict[str, Any] | None:
        """Store one part; returns {key: value} for every stream once the frame is complete.

        A repeated (key, stamp) replaces the earlier part. Completing a frame removes it.
        """
        if key not in self._pending:
            raise InputError("key", key, f"one of {list(self.keys)}")
        stamp_ns = int(stamp_ns)
        self._pending[key][stamp_ns] = value
        complete = None
        if all(stamp_ns in parts for parts in self._pending.values()):
            complete = {k: self._pending[k].pop(stamp_ns) for k in self.keys}
            self._expire(stamp_ns - self.max_age_ns)
        self._cap()
        return complete

    def _expire(self, horizon_ns: int) -> None:
        for key, parts in self._pending.items():
            for stamp in [s for s in parts if s < horizon_ns]:
                del parts[stamp]
                self._dropped.append(
                    Dropped(
                        key, stamp, f"no matching {self._missing(stamp, key)} within the age limit"
                    )
                )

    def _cap(self) -> None:
        for key, parts in self._pending.items():
            while len(parts) > self._caps[key]:
                stamp = min(parts)
                del parts[stamp]
                self._dropped.append(
                    Dropped(key, stamp, f"more than {self._caps[key]} {key} parts waiting")
                )

    def _missing(self, stamp_ns: int, key: str) -> str:
        return (
            "/".join(k for k in self.keys if k != key and stamp_ns not in self._pending[k])
            or "part"
        )

    def pop_dropped(self) -> list[Dropped]:
        """The parts discarded since the last call (for logging), oldest first."""
        dropped, self._dropped = self._dropped, []
        return dropped

    def clear(self) -> int:
        """Forget every part waiting for partners; how many there were."""
        parts = sum(len(p) for p in self._pending.values())
        for p in self._pending.values():
            p.clear()
        return parts

    def pending(self, key: str) -> list[int]:
        """Stamps of the parts of stream `key` still waiting for partners, ascending."""
        return sorted(self._pending[key])


class HeldFrames:
    """Whole frames held until the camera info they need has arrived: a frame's topics arrive in
    any order, camera info included. Beyond `capacity` frames the oldest is dropped (counted in
    `dropped`)."""

    def __init__(self, capacity: int) -> None:
        self._held: deque[tuple[int, Any]] = deque(maxlen=capacity)
        self.dropped = 0  # frames dropped: `capacity` newer ones were held

    def hold(self, stamp_ns: int, frame: Any, info_topic: str) -> str | None:
        """Hold a whole frame; for the first one held since the last release, the warning to log
        (None otherwise: said once, not per frame)."""
        first = not self._held
        self.dropped += len(self._held) == self._held.maxlen
        self._held.append((stamp_ns, frame))
        return (
            f"no camera_info on {info_topic} yet; holding frames until it arrives"
            if first
            else None
        )

    def release(self) -> list[tuple[int, Any]]:
        """Every frame held, oldest first, and none held any more."""
        frames = list(self._held)
        self._held.clear()
        return frames

    def __len__(self) -> int:
        return len(self._held)


class CameraInfoCache:
    """The camera info of the last `size` stamps: a frame takes its own stamp's, else the latest
    (intrinsics rarely change), else none yet (`None`: hold the frame, `HeldFrames`)."""

    def __init__(self, size: int) -> None:
        self.size = int(size)
        self._by_stamp: OrderedDict[int, Any] = OrderedDict()
        self.latest: Any = None

    def add(self, stamp_ns: int, info: Any) -> None:
        self.latest = info
        self._by_stamp[int(stamp_ns)] = info
        while len(self._by_stamp) > self.size:
            self._by_stamp.popitem(last=False)

    def get(self, stamp_ns: int) -> Any:
        return self._by_stamp.get(int(stamp_ns), self.latest)
