"""Stamp pairing of the messages that make up one captured frame (color, depth, pose).

Every message of a frame carries the capture stamp of its source frame, so a frame is complete when
each stream has delivered a message with the same `stamp_ns`, or (`slop_ns` > 0, the approximate
time policy of `message_filters`) with a stamp within `slop_ns` of the reference stream's (the
first key): drivers that stamp colour and depth a few milliseconds apart. Entries wait in one small dict per
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

import bisect
from collections import OrderedDict, deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from area3d_msgs_py.errors import InputError

# Keep unmatched parts for 5 s of stamp time (our choice: well above one render + transport).
MAX_AGE_NS = 5_000_000_000
# Hard cap on waiting entries per stream, whatever their age (a stuck stream must not grow memory).
MAX_PENDING = 64
# The pairing rate is measured over this many frames of the reference stream.
RATE_WINDOW = 100
# Frames that never arrived at all are estimated from the gaps between the reference stream's
# stamps (`count_gaps`): the stream's period is the median of the single-period gaps among its
# last GAP_WINDOW (frames that came back to back, `_period`), counted only for a stream of at
# least 5 Hz whose gaps are whole periods, and a gap longer than MAX_GAP_NS is a pause of the
# camera, not frames lost.
GAP_WINDOW = 50
MIN_GAPS = 10
MAX_PERIOD_NS = 200_000_000
MAX_GAP_NS = 1_000_000_000
# a gap within this many periods of a whole number of them is that many periods (camera jitter)
PERIOD_TOLERANCE = 0.2


class Paired(NamedTuple):
    """A complete frame: the reference stream's stamp and {key: value} of every stream."""

    stamp_ns: int
    parts: dict


@dataclass(frozen=True)
class Dropped:
    """A part that was discarded without a partner: its stream, its stamp and why."""

    key: str
    stamp_ns: int
    reason: str


def _period(gaps) -> float:
    """A stream's period from its recent gaps: their median, when nine gaps in ten are whole
    multiples of it (most frames arrive: a frame published late, then the next on time, leaves a
    short gap that is no period); else the shortest gaps' median (those within 1.25 times the
    shortest of the gaps at least half the 10th percentile: two parts of one frame sent twice are
    not a period), or its half or third, whichever makes nine gaps in ten whole. A stream that
    seldom sends two frames in a row (a third lost and a driver often late: measured beside a
    loaded 30 Hz driver) has gaps of two and three periods, whose shortest is two; every gap then
    would read as half the frames it lost. 0.0 when none does: a stream stamped irregularly (a
    driver stamping on publish, late by up to most of a period under load) says nothing by its
    gaps of what it lost, and its shortest gaps read as a period a fraction of the real one,
    every frame as several lost."""
    ordered = sorted(gaps)
    floor = 0.5 * ordered[len(ordered) // 10]
    counted = [g for g in ordered if g >= floor]
    shortest = counted[0]
    cluster = [g for g in counted if g <= 1.25 * shortest]
    base = cluster[len(cluster) // 2]
    for period in (counted[len(counted) // 2], base, base / 2, base / 3):
        whole = sum(abs(g / period - round(g / period)) <= PERIOD_TOLERANCE for g in counted)
        if whole >= 0.9 * len(counted):
            return period
    return 0.0


class StampSync:
    """Pairs messages of several streams by stamp: identical, or within `slop_ns` of the
    reference stream's (the first key) when `slop_ns` > 0, the closest part of each stream.

    keys: the stream names that make a complete frame, e.g. ("color", "depth", "pose").
    max_pending: the cap on waiting parts per stream; `pending_caps` overrides it per stream (a
    pose is 128 bytes and may wait in thousands for images that trail it).
    count_gaps: count the reference stream's frames that never arrived (`frames_missed`), against
    `period_ns`, its nominal period (a driver's rate), or with 0 against the period learnt from
    the gaps (`_period`: right while most frames arrive, and only for a stream of at least 5 Hz).
    """

    def __init__(
        self,
        keys: Sequence[str],
        max_age_ns: int = MAX_AGE_NS,
        max_pending: int = MAX_PENDING,
        pending_caps: dict[str, int] | None = None,
        slop_ns: int = 0,
        count_gaps: bool = False,
        period_ns: int = 0,
    ) -> None:
        if len(keys) == 0 or len(set(keys)) != len(keys):
            raise InputError("keys", list(keys), "one or more distinct stream names")
        if max_age_ns < 0:
            raise InputError("max_age_ns", max_age_ns, "a duration >= 0 nanoseconds")
        if slop_ns < 0:
            raise InputError("slop_ns", slop_ns, "a duration >= 0 nanoseconds")
        if period_ns < 0:
            raise InputError("period_ns", period_ns, "a duration >= 0 nanoseconds (0: learnt)")
        if max_pending < 1:
            raise InputError("max_pending", max_pending, "an integer >= 1")
        self.keys = tuple(keys)
        self.max_age_ns = int(max_age_ns)
        self.max_pending = int(max_pending)
        self._caps = {k: int((pending_caps or {}).get(k, max_pending)) for k in self.keys}
        if min(self._caps.values()) < 1:
            raise InputError("pending_caps", pending_caps, "integers >= 1")
        self.slop_ns = int(slop_ns)
        self._pending: dict[str, dict[int, Any]] = {k: {} for k in self.keys}
        self._sorted: dict[str, list[int]] = {k: [] for k in self.keys}  # the stamps, ascending
        self._dropped: list[Dropped] = []
        self.frames_paired = 0  # complete frames handed out
        self.parts_dropped = 0  # parts discarded without partners (every stream)
        # the reference stream's last RATE_WINDOW frames: True paired, False dropped or missed
        self._outcomes: deque[bool] = deque(maxlen=RATE_WINDOW)
        self.count_gaps = count_gaps
        self.period_ns = int(period_ns)  # the reference stream's nominal period; 0: learnt
        self.frames_missed = 0  # reference frames that never arrived (estimated from the gaps)
        self._gaps: deque[int] = deque(maxlen=GAP_WINDOW)
        self._last_reference: int | None = None
        self._last_missed = 0  # frames the last gap counted as missed

    def add(self, key: str, stamp_ns: int, value: Any) -> dict[str, Any] | None:
        """Store one part; returns {key: value} for every stream once the frame is complete
        (`add_part` also says the frame's stamp)."""
        paired = self.add_part(key, stamp_ns, value)
        return None if paired is None else paired.parts

    def add_part(self, key: str, stamp_ns: int, value: Any) -> Paired | None:
        """Store one part; returns the frame (the reference stream's stamp and {key: value} for
        every stream) once it is complete.

        A repeated (key, stamp) replaces the earlier part. Completing a frame removes its parts.
        """
        if key not in self._pending:
            raise InputError("key", key, f"one of {list(self.keys)}")
        stamp_ns = int(stamp_ns)
        if key == self.keys[0] and self.count_gaps:
            self._count_gap(stamp_ns)
        if stamp_ns not in self._pending[key]:
            bisect.insort(self._sorted[key], stamp_ns)
        self._pending[key][stamp_ns] = value
        complete = self._complete(key, stamp_ns)
        if complete is not None:
            self.frames_paired += 1
            self._outcomes.append(True)
            self._expire(complete.stamp_ns - self.max_age_ns)
        self._cap()
        return complete

    def _count_gap(self, stamp_ns: int) -> None:
        """Frames the reference stream skipped before `stamp_ns`: a gap of n periods is n - 1
        frames that never arrived (a streaming camera's frames lost on the way). A frame
        stamped less than half a period after, or before, the end of a gap counted as frames
        lost takes one back: the frame at that end was published late by more than half a
        period, not after a lost one."""
        last, self._last_reference = self._last_reference, stamp_ns
        if last is None or stamp_ns <= last:
            self._last_reference = last if last is not None else stamp_ns
            if last is not None and stamp_ns < last and self._last_missed > 0:
                self._last_missed -= 1  # it arrived after a later one: in that gap
                self.frames_missed -= 1
                self._take_back_missed()
            return
        gap = stamp_ns - last
        counted, self._last_missed = self._last_missed, 0
        if gap <= MAX_GAP_NS and (self.period_ns or len(self._gaps) >= MIN_GAPS):
            period = self.period_ns or _period(self._gaps)
            if self.period_ns or 0 < period <= MAX_PERIOD_NS:
                missed = int(round(gap / period)) - 1
                if missed > 0:
                    self.frames_missed += missed
                    self._outcomes.extend([False] * missed)
                    self._last_missed = missed
                elif missed < 0 and counted > 0:
                    self.frames_missed -= 1
                    self._take_back_missed()
        self._gaps.append(gap)

    def _take_back_missed(self) -> None:
        """Remove the newest False (a frame counted as missed) from the rate's window."""
        for i in range(len(self._outcomes) - 1, -1, -1):
            if not self._outcomes[i]:
                del self._outcomes[i]
                return

    def _closest(self, key: str, stamp_ns: int) -> int | None:
        """The stamp of `key`'s waiting part closest to `stamp_ns`, within the slop; None if
        there is none."""
        if self.slop_ns == 0:
            return stamp_ns if stamp_ns in self._pending[key] else None
        stamps = self._sorted[key]
        i = bisect.bisect_left(stamps, stamp_ns)
        near = [s for s in stamps[max(0, i - 1) : i + 1] if abs(s - stamp_ns) <= self.slop_ns]
        return min(near, key=lambda s: abs(s - stamp_ns)) if near else None

    def _complete(self, key: str, stamp_ns: int) -> Paired | None:
        """The frame the part (key, stamp_ns) completes, its parts taken out; None if none."""
        ref = self.keys[0]
        if key == ref:
            references = [stamp_ns]
        else:  # reference parts within the slop, closest first
            stamps = self._sorted[ref]
            lo = bisect.bisect_left(stamps, stamp_ns - self.slop_ns)
            hi = bisect.bisect_right(stamps, stamp_ns + self.slop_ns)
            references = sorted(stamps[lo:hi], key=lambda s: abs(s - stamp_ns))
        for reference in references:
            chosen = {ref: reference}
            for k in self.keys[1:]:
                s = stamp_ns if k == key else self._closest(k, reference)
                if s is None or abs(s - reference) > self.slop_ns:
                    break
                chosen[k] = s
            else:
                return Paired(reference, {k: self._take(k, s) for k, s in chosen.items()})
        return None

    def _take(self, key: str, stamp_ns: int) -> Any:
        self._sorted[key].remove(stamp_ns)
        return self._pending[key].pop(stamp_ns)

    def _drop(self, key: str, stamp_ns: int, reason: str) -> None:
        self._take(key, stamp_ns)
        self.parts_dropped += 1
        if key == self.keys[0]:
            self._outcomes.append(False)
        self._dropped.append(Dropped(key, stamp_ns, reason))

    def _expire(self, horizon_ns: int) -> None:
        for key in self.keys:
            for stamp in [s for s in self._sorted[key] if s < horizon_ns]:
                missing = self._missing(stamp, key)
                self._drop(key, stamp, f"no matching {missing} within the age limit")

    def _cap(self) -> None:
        for key in self.keys:
            while len(self._sorted[key]) > self._caps[key]:
                stamp = self._sorted[key][0]
                self._drop(key, stamp, f"more than {self._caps[key]} {key} parts waiting")

    def _missing(self, stamp_ns: int, key: str) -> str:
        return (
            "/".join(k for k in self.keys if k != key and self._closest(k, stamp_ns) is None)
            or "part"
        )

    def pairing_rate(self) -> float | None:
        """The share of the reference stream's last frames (up to RATE_WINDOW) that paired into a
        frame: a part dropped without partners, or (`count_gaps`) a frame missing from the
        stream, counts against it; None before any paired or was lost. Parts still waiting do
        not count."""
        if not self._outcomes:
            return None
        return sum(self._outcomes) / len(self._outcomes)

    def pop_dropped(self) -> list[Dropped]:
        """The parts discarded since the last call (for logging), oldest first."""
        dropped, self._dropped = self._dropped, []
        return dropped

    def clear(self) -> int:
        """Forget every part waiting for partners; how many there were."""
        parts = sum(len(p) for p in self._pending.values())
        for key in self.keys:
            self._pending[key].clear()
            self._sorted[key].clear()
        return parts

    def pending(self, key: str) -> list[int]:
        """Stamps of the parts of stream `key` still waiting for partners, ascending."""
        return list(self._sorted[key])


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


def pairing_warning(sync: StampSync, min_rate: float) -> str | None:
    """The node's standing warning when the share of frames paired fell below `min_rate` (its
    status `warnings`, WARN on /diagnostics); None while it holds or nothing was paired yet."""
    rate = sync.pairing_rate()
    if rate is None or rate >= min_rate:
        return None
    return (
        f"pairing rate {rate:.2f} below min_pairing_rate {min_rate:g}: parts of frames are lost "
        "on the way (best effort, a reader queue too short) or stamped further apart than "
        "sync_slop_s"
    )
