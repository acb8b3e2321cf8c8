"""Camera poses at an image's stamp, from TF or from a pose stream: a transform buffer on numpy.

What tf2's buffer does, without ROS: transforms arrive per edge (parent -> child, the pose of
`child` in `parent`, as in geometry_msgs/TransformStamped) with their own stamps and rates; a
lookup of `target -> source` at a stamp chains the edges through their common ancestor,
interpolating each dynamic edge between the two samples around the stamp (linear in translation,
slerp in rotation). Static edges (`/tf_static`) hold at every stamp. As in tf2 there is no
extrapolation: a stamp outside an edge's samples fails, unless it lies within `tolerance_s` of the
nearest sample, which is then used as it is (clamped).

Samples are checked where they enter (`TransformBuffer.add`), each rejection an `InputError` naming
the message field, the value and what was expected: empty or equal frame names, a second parent
for a frame or a loop, a stamp <= 0 or further ahead of the receiver's clock than `max_ahead_s`,
non-finite values, a quaternion off unit length, and a jump (faster than `max_linear_speed` or
`max_angular_speed` from the previous sample of that edge). A lookup that cannot be answered raises
`LookupFailure` with one of five causes (no transform yet, too old, in the future, disconnected,
a gap: the samples around the stamp further apart than `max_interval_s`, where nobody knows how
the frame moved), so that a node can count and log each cause once.

Conventions: poses are 4x4 float64 homogeneous matrices; quaternions are (x, y, z, w) as in ROS;
stamps are int nanoseconds; `lookup(target, source)` returns T_target_source, which maps points in
`source` to `target` (the pose of `source` in `target`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.rotations import (
    check_quaternion,
    check_translation,
    invert,
    matrix,
    rotation_angle,
    rotation_to_quaternion,
    slerp,
)

NS_PER_S = 1_000_000_000
# tf2's default cache time: how much history each dynamic edge keeps, counted back from its newest.
DEFAULT_HISTORY_S = 10.0
# As for every input of the graph (area3d_msgs_py.inputs): clock skew allowed between hosts.
DEFAULT_MAX_AHEAD_S = 5.0


class StampedTransform(NamedTuple):
    """One edge sample: the pose `T` (4x4) of frame `child` in frame `parent` at `stamp_ns`."""

    parent: str
    child: str
    stamp_ns: int
    T: np.ndarray


@dataclass(frozen=True)
class Fields:
    """The message fields a sample's parts came from, named in rejections."""

    parent: str = "header.frame_id"
    child: str = "child_frame_id"
    stamp: str = "header.stamp"
    translation: str = "transform.translation"
    rotation: str = "transform.rotation"


TF_FIELDS = Fields()  # geometry_msgs/TransformStamped (in tf2_msgs/TFMessage)
POSE_FIELDS = Fields(translation="pose.position", rotation="pose.orientation")  # PoseStamped
ODOMETRY_FIELDS = Fields(translation="pose.pose.position", rotation="pose.pose.orientation")


class LookupFailure(LookupError):
    """A transform that cannot be had at the stamp asked for; `cause` is one of the five below."""

    NO_TRANSFORM = "no_transform"  # a frame has never been seen (nothing published for it yet)
    TOO_OLD = "too_old"  # before an edge's oldest sample kept, beyond the tolerance
    IN_FUTURE = "in_future"  # after an edge's newest sample, beyond the tolerance (not arrived yet)
    DISCONNECTED = "disconnected"  # both frames known, in two trees with no common ancestor
    GAP = "gap"  # between two samples of an edge further apart than max_interval_s
    CAUSES = (NO_TRANSFORM, TOO_OLD, IN_FUTURE, DISCONNECTED, GAP)

    def __init__(self, cause: str, message: str) -> None:
        self.cause = cause
        super().__init__(message)

    def __reduce__(self):
        return (type(self), (self.cause, str(self)))


# one edge's samples ------------------------------------------------------------------------------
class _History:
    """Samples of one dynamic edge, sorted by stamp, in arrays that grow by doubling; the oldest are
    dropped once they are more than `history_ns` older than the newest."""

    def __init__(self, history_ns: int, capacity: int = 16) -> None:
        self.history_ns = history_ns
        self.stamps = np.empty(capacity, np.int64)
        self.translations = np.empty((capacity, 3))
        self.rotations = np.empty((capacity, 4))
        self.start = 0
        self.end = 0

    def __len__(self) -> int:
        return self.end - self.start

    def view(self) -> np.ndarray:
        return self.stamps[self.start : self.end]

    def index_at_or_before(self, stamp_ns: int) -> int | None:
        """Absolute index of the newest sample at or before `stamp_ns`, None when there is none."""
        i = int(np.searchsorted(self.view(), stamp_ns, side="right")) + self.start - 1
        return i if i >= self.start else None

    def insert(self, stamp_ns: int, translation: np.ndarray, rotation: np.ndarray) -> None:
        if self.end == len(self.stamps):
            self._make_room()
        i = int(np.searchsorted(self.view(), stamp_ns)) + self.start
        if i < self.end:  # out of order: shift the newer samples by one
            for array in (self.stamps, self.translations, self.rotations):
                array[i + 1 : self.end + 1] = array[i : self.end]
        self.stamps[i] = stamp_ns
        self.translations[i] = translation
        self.rotations[i] = rotation
        self.end += 1
        oldest_kept = self.stamps[self.end - 1] - self.history_ns
        self.start += int(np.searchsorted(self.view(), oldest_kept))

    def _make_room(self) -> None:
        n = len(self)
        capacity = len(self.stamps) if n <= len(self.stamps) // 2 else 2 * len(self.stamps)
        arrays = []
        for array in (self.stamps, self.translations, self.rotations):
            grown = np.empty((capacity,) + array.shape[1:], array.dtype)
            grown[:n] = array[self.start : self.end]
            arrays.append(grown)
        self.stamps, self.translations, self.rotations = arrays
        self.start, self.end = 0, n


@dataclass
class _Edge:
    parent: str
    static: np.ndarray | None  # the 4x4 of a static edge
    history: _History | None  # the samples of a dynamic edge


# the buffer --------------------------------------------------------------------------------------
class TransformBuffer:
    """A TF tree's transforms by edge, with a bounded history; lookups at a stamp.

    history_s: how long each dynamic edge's samples are kept, back from its newest (tf2: 10 s).
    tolerance_s: how far outside an edge's samples a lookup may ask; the nearest sample is used as
        it is (no extrapolation). 0 = only stamps between two samples (or at one), as tf2.
    max_linear_speed: m/s; a sample implying a faster translation from the previous sample of its
        edge is refused as a jump. None = not checked. The previous sample is the one kept just
        before it in time; one more than history_s older is not compared with (the edge starts
        afresh), so a real relocation is accepted once history_s has passed.
    max_angular_speed: rad/s; the same for rotation. None = not checked.
    max_ahead_s: a dynamic sample's stamp may be at most this far ahead of the receiver's clock
        (`now_ns` given to `add`).
    max_interval_s: a stamp between two samples of a dynamic edge further apart than this fails
        (`gap`): the transforms paused (an odometry outage) and the frame may have moved in any
        way meanwhile; tf2 interpolates across any gap. 0 = no limit.

    Not thread-safe: a node whose callbacks run on several threads holds one lock around `add`
    and `lookup`.
    """

    def __init__(
        self,
        history_s: float = DEFAULT_HISTORY_S,
        tolerance_s: float = 0.0,
        max_linear_speed: float | None = None,
        max_angular_speed: float | None = None,
        max_ahead_s: float = DEFAULT_MAX_AHEAD_S,
        max_interval_s: float = 0.0,
    ) -> None:
        for name, value in (
            ("history_s", history_s),
            ("tolerance_s", tolerance_s),
            ("max_ahead_s", max_ahead_s),
            ("max_interval_s", max_interval_s),
            ("max_linear_speed", max_linear_speed),
            ("max_angular_speed", max_angular_speed),
        ):
            if value is not None and not (np.isfinite(value) and value >= 0):
                raise InputError(name, value, "a finite number >= 0")
        if history_s <= 0:
            raise InputError("history_s", history_s, "seconds > 0")
        self.history_ns = int(history_s * NS_PER_S)
        self.tolerance_ns = int(tolerance_s * NS_PER_S)
        self.max_linear_speed = max_linear_speed
        self.max_angular_speed = max_angular_speed
        self.max_ahead_ns = int(max_ahead_s * NS_PER_S)
        self.max_interval_ns = int(max_interval_s * NS_PER_S)
        self._edges: dict[str, _Edge] = {}  # by child frame: each frame has one parent

    # input ---------------------------------------------------------------------------------------
    def add(
        self,
        parent: str,
        child: str,
        stamp_ns: int,
        translation: Any,
        rotation: Any,
        *,
        static: bool = False,
        now_ns: int | None = None,
        fields: Fields = TF_FIELDS,
    ) -> bool:
        """Add one sample of edge parent -> child (translation (3,) m, rotation (x, y, z, w)).

        A static edge holds at every stamp and is replaced by a later static sample. Returns False
        when the edge already has a sample at this stamp (the first one is kept, as tf2 does);
        raises InputError naming the field of a sample refused.
        """
        self._check_edge(parent, child, static, fields)
        t = check_translation(translation, fields.translation)
        q = check_quaternion(rotation, fields.rotation)
        stamp_ns = int(stamp_ns)
        if static:
            self._edges[child] = _Edge(parent, matrix(t, q), None)
            return True
        if stamp_ns <= 0:
            raise InputError(fields.stamp, stamp_ns, "a stamp > 0 ns since the epoch")
        if now_ns is not None and stamp_ns > now_ns + self.max_ahead_ns:
            raise InputError(
                fields.stamp,
                stamp_ns,
                f"a stamp at most {self.max_ahead_ns / NS_PER_S:g} s ahead of this node's clock "
                f"({now_ns} ns)",
            )
        edge = self._edges.get(child)
        if edge is None:
            edge = self._edges[child] = _Edge(parent, None, _History(self.history_ns))
        history = edge.history
        before = history.index_at_or_before(stamp_ns)
        if before is not None and history.stamps[before] == stamp_ns:
            return False
        if before is not None and stamp_ns - history.stamps[before] <= self.history_ns:
            self._check_jump(history, before, stamp_ns, t, q, fields)
        history.insert(stamp_ns, t, q)
        return True

    def _check_edge(self, parent: str, child: str, static: bool, fields: Fields) -> None:
        if not isinstance(parent, str) or not parent:
            raise InputError(fields.parent, parent, "the parent frame's name")
        if not isinstance(child, str) or not child:
            raise InputError(fields.child, child, "the child frame's name")
        if parent == child:
            raise InputError(fields.child, child, f"a frame other than its parent {parent!r}")
        edge = self._edges.get(child)
        if edge is not None:
            if edge.parent != parent:
                raise InputError(
                    fields.parent,
                    parent,
                    f"{edge.parent!r}, the parent {child!r} already has (a frame has one parent)",
                )
            if (edge.static is not None) != static:
                kind = "static" if edge.static is not None else "dynamic"
                raise InputError(
                    fields.child,
                    child,
                    f"a frame whose edge from {parent!r} is not already {kind} "
                    f"(/tf_static and /tf may not both carry it)",
                )
            return
        frame = parent
        while frame in self._edges:  # a new edge must not close a loop
            frame = self._edges[frame].parent
            if frame == child:
                raise InputError(
                    fields.child, child, f"a frame that is not an ancestor of {parent!r} (no loops)"
                )

    def _check_jump(
        self,
        history: _History,
        before: int,
        stamp_ns: int,
        t: np.ndarray,
        q: np.ndarray,
        fields: Fields,
    ) -> None:
        """Refuse a sample that moves faster than the limits from the previous one kept."""
        previous_ns = int(history.stamps[before])
        dt = (stamp_ns - previous_ns) / NS_PER_S
        if self.max_linear_speed is not None:
            speed = float(np.linalg.norm(t - history.translations[before])) / dt
            if speed > self.max_linear_speed:
                raise InputError(
                    fields.translation,
                    t.tolist(),
                    f"a translation within max_linear_speed {self.max_linear_speed:g} m/s of the "
                    f"previous sample ({speed:.3g} m/s from {history.translations[before].tolist()} "
                    f"at {previous_ns} ns): a jump",
                )
        if self.max_angular_speed is not None:
            speed = rotation_angle(q, history.rotations[before]) / dt
            if speed > self.max_angular_speed:
                raise InputError(
                    fields.rotation,
                    q.tolist(),
                    f"a rotation within max_angular_speed {self.max_angular_speed:g} rad/s of the "
                    f"previous sample ({speed:.3g} rad/s from {history.rotations[before].tolist()} "
                    f"at {previous_ns} ns): a jump",
                )

    # output --------------------------------------------------------------------------------------
    def frames(self) -> set[str]:
        """Every frame seen, as a parent or a child."""
        return set(self._edges) | {edge.parent for edge in self._edges.values()}

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """T_target_source (4x4) at `stamp_ns`: the pose of `source` in `target`, each dynamic edge
        interpolated between its samples around the stamp. Raises LookupFailure."""
        known = self.frames()
        for frame in (target, source):
            if frame not in known:
                raise LookupFailure(
                    LookupFailure.NO_TRANSFORM,
                    f"no transform for frame {frame!r} yet (frames known: {sorted(known)})",
                )
        up_source = self._path_to_root(source)
        up_target = self._path_to_root(target)
        on_target_path = set(up_target)
        common = next((frame for frame in up_source if frame in on_target_path), None)
        if common is None:
            raise LookupFailure(
                LookupFailure.DISCONNECTED,
                f"{target!r} and {source!r} are not connected: their trees' roots are "
                f"{up_target[-1]!r} and {up_source[-1]!r} (is an edge between them published?)",
            )
        T_common_source = self._chain(up_source, common, int(stamp_ns))
        T_common_target = self._chain(up_target, common, int(stamp_ns))
        return invert(T_common_target) @ T_common_source

    def _path_to_root(self, frame: str) -> list[str]:
        path = [frame]
        while path[-1] in self._edges:
            path.append(self._edges[path[-1]].parent)
        return path

    def _chain(self, path: list[str], common: str, stamp_ns: int) -> np.ndarray:
        """T_common_path[0] along `path` (a frame, its parent, ... up to `common`)."""
        T = np.eye(4)
        for child in path[: path.index(common)]:
            T = self._edge_at(child, stamp_ns) @ T
        return T

    def _edge_at(self, child: str, stamp_ns: int) -> np.ndarray:
        edge = self._edges[child]
        if edge.static is not None:
            return edge.static
        history = edge.history
        stamps = history.view()
        i = int(np.searchsorted(stamps, stamp_ns))  # first sample at or after the stamp
        start = history.start
        if i < len(stamps) and stamps[i] == stamp_ns:
            k = start + i
            return matrix(history.translations[k], history.rotations[k])
        if i == 0 or i == len(stamps):
            nearest = 0 if i == 0 else len(stamps) - 1
            gap_ns = abs(int(stamps[nearest]) - stamp_ns)
            if gap_ns > self.tolerance_ns:
                raise self._outside(edge.parent, child, stamp_ns, stamps, i == 0, gap_ns)
            k = start + nearest
            return matrix(history.translations[k], history.rotations[k])
        k0, k1 = start + i - 1, start + i
        before, after = int(stamps[i - 1]), int(stamps[i])
        if self.max_interval_ns and after - before > self.max_interval_ns:
            raise LookupFailure(
                LookupFailure.GAP,
                f"stamp {stamp_ns} falls between transforms {edge.parent!r} -> {child!r} at "
                f"{before} and {after} ns, {(after - before) / NS_PER_S:.3f} s apart, more than "
                f"max_interval_s {self.max_interval_ns / NS_PER_S:g}: the transforms paused and "
                "where the frame was meanwhile is not known",
            )
        u = (stamp_ns - before) / (after - before)
        t = (1.0 - u) * history.translations[k0] + u * history.translations[k1]
        return matrix(t, slerp(history.rotations[k0], history.rotations[k1], u))

    def _outside(
        self,
        parent: str,
        child: str,
        stamp_ns: int,
        stamps: np.ndarray,
        before: bool,
        gap_ns: int,
    ) -> LookupFailure:
        span = f"samples {int(stamps[0])}..{int(stamps[-1])} ns"
        tolerance = f"tolerance_s {self.tolerance_ns / NS_PER_S:g}"
        if before:
            return LookupFailure(
                LookupFailure.TOO_OLD,
                f"stamp {stamp_ns} is {gap_ns / NS_PER_S:.3f} s before the oldest transform "
                f"{parent!r} -> {child!r} kept ({span}, history_s {self.history_ns / NS_PER_S:g}, "
                f"{tolerance})",
            )
        return LookupFailure(
            LookupFailure.IN_FUTURE,
            f"stamp {stamp_ns} is {gap_ns / NS_PER_S:.3f} s after the newest transform "
            f"{parent!r} -> {child!r} ({span}, {tolerance}): it has not arrived yet",
        )


class PoseStream:
    """Poses from a pose topic at its own rate (geometry_msgs/PoseStamped, or nav_msgs/Odometry
    with a fixed body-to-camera transform), interpolated to an image's stamp.

    world_frame: the frame the poses are in (their header.frame_id must be it).
    body_frame: the odometry's child_frame_id (checked when given); for a PoseStamped of the camera
        itself leave it None and T_body_camera the identity.
    T_body_camera: 4x4 pose of the camera (its optical frame) in the body frame.
    fields: the message fields named in rejections (POSE_FIELDS, ODOMETRY_FIELDS).
    The other arguments are TransformBuffer's.
    """

    # Names of the buffer's own frames (a ROS frame name has no parentheses).
    BODY = "(body)"
    CAMERA = "(camera)"

    def __init__(
        self,
        world_frame: str,
        body_frame: str | None = None,
        T_body_camera: np.ndarray | None = None,
        fields: Fields = POSE_FIELDS,
        **limits: Any,
    ) -> None:
        if not isinstance(world_frame, str) or not world_frame:
            raise InputError("world_frame", world_frame, "the frame the poses are expressed in")
        self.world_frame = world_frame
        self.body_frame = body_frame
        self.fields = fields
        self.buffer = TransformBuffer(**limits)
        T = np.eye(4) if T_body_camera is None else np.asarray(T_body_camera, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise InputError("T_body_camera", T.tolist(), "a finite 4x4 rigid transform")
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise InputError("T_body_camera", T.tolist(), "a rotation that is orthonormal")
        self.buffer.add(self.BODY, self.CAMERA, 0, T[:3, 3], rotation_to_quaternion(R), static=True)

    def add(
        self,
        stamp_ns: int,
        position: Any,
        orientation: Any,
        frame_id: str,
        child_frame_id: str | None = None,
        now_ns: int | None = None,
    ) -> bool:
        """Add one pose of the body in world_frame; see TransformBuffer.add."""
        if frame_id != self.world_frame:
            raise InputError(self.fields.parent, frame_id, f"{self.world_frame!r} (world_frame)")
        if self.body_frame is not None and child_frame_id != self.body_frame:
            raise InputError(self.fields.child, child_frame_id, f"{self.body_frame!r}")
        return self.buffer.add(
            self.world_frame,
            self.BODY,
            stamp_ns,
            position,
            orientation,
            now_ns=now_ns,
            fields=self.fields,
        )

    def pose_at(self, stamp_ns: int) -> np.ndarray:
        """T_world_camera (4x4) at `stamp_ns`; raises LookupFailure."""
        if self.BODY not in self.buffer.frames():
            raise LookupFailure(
                LookupFailure.NO_TRANSFORM,
                f"no pose in {self.world_frame!r} received yet",
            )
        return self.buffer.lookup(self.world_frame, self.CAMERA, stamp_ns)
