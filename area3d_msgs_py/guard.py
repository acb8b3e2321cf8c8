"""Callbacks that log bad input instead of ending the node, and count what they rejected.

rclpy lets an exception raised in a callback end ``spin()``, and with it the node; a malformed
message from another process must not do that. ``guarded(node, callback, what, rejections)`` logs
the error (an ``InputError`` as one line naming field, value and expectation; anything else with
its traceback) and returns None. With a ``Rejections`` it also counts the rejection under the topic
and the field, so the node's status topic can say what it refused (a hostile or broken publisher
shows up there, not only in a log nobody reads). A refusal of the same topic and field repeats
at the publisher's rate (a driver's 50 Hz odometry with a bad quaternion): it is logged at most
once every LOG_PERIOD_S, saying how many like it were not; the counts stay exact. A reader whose
topic has a writer offering a QoS it cannot match gets nothing from it, which no callback sees:
`Rejections.qos_events` logs it once, by the topic's remapped name, and keeps it in the status
(`incompatible_qos`), which `/diagnostics` reports as a standing warning.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import InvalidHandle
from rclpy.qos import QoSPolicyKind

from area3d_msgs_py.errors import InputError

LOG_PERIOD_S = 1.0


class Rejections:
    """Thread-safe counts of rejected inputs per topic and per field (the InputError's field).

    >>> r = Rejections(); r.count("area3d/camera/pose", "orientation"); r.snapshot()["total"]
    1
    """

    def __init__(
        self,
        on_count: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._lock = threading.Lock()
        self._by_topic: Counter[str] = Counter()
        self._by_field: Counter[str] = Counter()
        self._on_count = on_count  # e.g. publish the status soon
        self._clock = clock
        # (topic, field): [when one was last logged, how many since were not]
        self._logged: dict[tuple[str, str], list] = {}
        # topic as subscribed: (as remapped, the QoS policy at odds), until a message arrives
        self._incompatible: dict[str, tuple[str, str]] = {}

    def qos_events(self, node: Any, topic: str) -> SubscriptionEventCallbacks:
        """`event_callbacks` for the node's reader of `topic`: a writer offering a QoS the reader
        cannot match (a best-effort driver beside a reliable reader) is logged once and kept
        under `incompatible_qos` in the snapshot until a message arrives on it (`arrived`)."""

        def incompatible(info: Any) -> None:
            try:
                policy = QoSPolicyKind(info.last_policy_kind).name
            except ValueError:
                policy = str(info.last_policy_kind)
            name = node.resolve_topic_name(topic)
            with self._lock:
                first = topic not in self._incompatible
                self._incompatible[topic] = (name, policy)
            if first:
                hint = (
                    ": a best-effort writer, a reliable reader (camera_qos: sensor_data reads it)"
                    if policy == "RELIABILITY"
                    else ""
                )
                node.get_logger().warning(
                    f"{name}: a publisher offers a QoS this reader cannot match ({policy}"
                    f"{hint}); nothing it publishes arrives"
                )
            if self._on_count is not None:
                self._on_count()

        return SubscriptionEventCallbacks(incompatible_qos=incompatible)

    def to_log(self, topic: str, field: str) -> int | None:
        """None when this refusal goes unlogged (one of its topic and field was logged less than
        LOG_PERIOD_S ago); else how many like it were not logged since the last that was."""
        now = self._clock()
        with self._lock:
            last = self._logged.get((topic, field))
            if last is not None and now - last[0] < LOG_PERIOD_S:
                last[1] += 1
                return None
            self._logged[(topic, field)] = [now, 0]
            return 0 if last is None else last[1]

    def count(self, topic: str, field: str) -> None:
        with self._lock:
            self._by_topic[topic] += 1
            self._by_field[field] += 1
        if self._on_count is not None:
            self._on_count()

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._by_topic.values())

    def snapshot(self) -> dict:
        """{"total": n, "by_topic": {topic: n}, "by_field": {field: n}} (JSON-ready), and
        "incompatible_qos": {topic: policy} once a writer's QoS did not match a reader's."""
        with self._lock:
            snapshot = {
                "total": sum(self._by_topic.values()),
                "by_topic": dict(self._by_topic),
                "by_field": dict(self._by_field),
            }
            if self._incompatible:
                snapshot["incompatible_qos"] = dict(self._incompatible.values())
            return snapshot

    def arrived(self, topic: str) -> None:
        """A message arrived on `topic`: a writer reaches it now (the one at odds may have been
        restarted with a QoS that matches)."""
        if topic in self._incompatible:  # a dict lookup per message while nothing is at odds
            with self._lock:
                self._incompatible.pop(topic, None)


def reject(
    node: Any,
    rejections: Rejections | None,
    what: str,
    exc: InputError,
    topic: str | None = None,
) -> None:
    """Log one rejected input as a single warning line (with `rejections`, at most one a
    LOG_PERIOD_S per topic and field) and count it under `topic` (or `what`)."""
    key = topic or what
    unlogged = 0 if rejections is None else rejections.to_log(key, exc.field)
    if unlogged is not None:
        more = f" ({unlogged} more of {exc.field} refused since, not logged)" if unlogged else ""
        node.get_logger().warning(f"{what}: rejected: {exc}{more}")
    if rejections is not None:
        rejections.count(key, exc.field)


def _stamp_of(args: tuple) -> str:
    """The " at stamp N" of a stamped message, so the log line says which frame was refused."""
    try:
        stamp = args[0].header.stamp
        return f" at stamp {int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)}"
    except (AttributeError, IndexError, TypeError, ValueError):
        return ""


def guarded(
    node: Any, callback: Callable, what: str, rejections: Rejections | None = None
) -> Callable:
    def call(*args: Any) -> Any:
        try:
            if rejections is not None:
                rejections.arrived(what)
            try:
                return callback(*args)
            except InputError as exc:
                reject(node, rejections, what + _stamp_of(args), exc, topic=what)
            except InvalidHandle:
                pass  # a publisher or timer of a node being destroyed (shutdown): not an input's fault
            except Exception:
                node.get_logger().error(
                    f"{what}: exception, input dropped:\n{traceback.format_exc()}"
                )
                if rejections is not None:
                    rejections.count(what, "exception")
        except InvalidHandle:
            pass  # counting it touched the status timer of a node being destroyed
        return None

    call.__name__ = getattr(callback, "__name__", "callback")
    return call


def subscribe(
    node: Any,
    msg_type: type,
    topic: str,
    callback: Callable,
    qos_profile: Any,
    rejections: Rejections,
    **kwargs: Any,
) -> Any:
    """`node.create_subscription` for a topic another process publishes: the callback `guarded`
    (bad input logged and counted), and a writer whose QoS cannot reach the reader reported
    (`Rejections.qos_events`)."""
    return node.create_subscription(
        msg_type,
        topic,
        guarded(node, callback, topic, rejections),
        qos_profile,
        event_callbacks=rejections.qos_events(node, topic),
        **kwargs,
    )
