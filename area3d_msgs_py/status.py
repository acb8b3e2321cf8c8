"""A node's status line: JSON in std_msgs/String on area3d/<node>/status (`topics.*_STATUS`), and
the same facts as diagnostic_msgs/DiagnosticArray on /diagnostics (`area3d_msgs_py/diagnostics.py`
sets the level).

Published a moment after something changed (a frame processed, an input rejected), so a barrage of
bad messages yields one status line after it rather than one per message, and once a period as a
heartbeat: the diagnostics always (1 Hz, what the diagnostics tools expect), the JSON line where the
node asks for one, so `ros2 topic echo` shows the counters of a quiet node too. A node's worker
threads publish with `publish()` (inside the node's `PublishGate`).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from typing import Any

from rclpy.exceptions import InvalidHandle

from area3d_msgs_py import diagnostics, msgs, qos
from area3d_msgs_py.topics import Topic

CHANGE_DELAY_S = 0.05  # a burst of changes within this time yields one status line
HEARTBEAT_S = 1.0


class StatusPublisher:
    """Publishes `state()` as JSON on `topic` and as a DiagnosticArray on /diagnostics shortly
    after `changed()`; the diagnostics every HEARTBEAT_S too, the JSON line every `heartbeat_s`
    seconds unless it is None. `topic` None: the diagnostics only (a node whose status topic
    says something else, as the camera's per-goal line)."""

    def __init__(
        self,
        node: Any,
        topic: Topic | None,
        state: Callable[[], dict],
        heartbeat_s: float | None = HEARTBEAT_S,
    ) -> None:
        self._node = node
        self._state = state
        self._pub = (
            None if topic is None else node.create_publisher(msgs.String, topic.name, topic.qos())
        )
        self._diagnostics = node.create_publisher(
            diagnostics.DiagnosticArray, diagnostics.DIAGNOSTICS_TOPIC, qos.reliable()
        )
        self._name = diagnostics.status_name(node.get_fully_qualified_name())
        # the state at the last heartbeat: a level compares the counts with it
        self._lock = threading.Lock()
        self._last_heartbeat: dict | None = None
        self._json_heartbeat = heartbeat_s is not None and self._pub is not None
        self._soon = node.create_timer(CHANGE_DELAY_S, self._publish_soon)
        self._soon.cancel()
        node.create_timer(HEARTBEAT_S, self._heartbeat)

    def changed(self) -> None:
        """Something in the state changed: publish it shortly (repeated calls coalesce). From a
        worker thread this may come as the node is destroyed: its timer is gone, and so is anyone
        to tell (rclpy raised InvalidHandle on the semantics node's VLM thread as a test ended)."""
        try:
            self._soon.reset()
        except InvalidHandle:
            pass

    def _publish_soon(self) -> None:
        self._soon.cancel()
        self.publish()

    def _state_now(self) -> dict:
        """`state()`, with the messages the node's executor could not take (a `GuardedExecutor`'s
        `untaken`), per topic, once there are any."""
        state = self._state()
        untaken = getattr(getattr(self._node, "executor", None), "untaken", None)
        counts = untaken() if callable(untaken) else None
        return {**state, "messages_dropped_untaken": counts} if counts else state

    def _heartbeat(self) -> None:
        state = self._state_now()
        if self._json_heartbeat:
            self._pub.publish(msgs.String(data=json.dumps(state)))
        self._publish_diagnostics(state)
        with self._lock:
            self._last_heartbeat = state

    def publish(self) -> dict:
        """Publish the state now (JSON and diagnostics); returns it."""
        state = self._state_now()
        if self._pub is not None:
            self._pub.publish(msgs.String(data=json.dumps(state)))
        self._publish_diagnostics(state)
        return state

    def _publish_diagnostics(self, state: dict) -> None:
        with self._lock:
            baseline = self._last_heartbeat
        status = diagnostics.diagnostic_status(
            self._name, state, baseline, hardware_id=self._node.get_fully_qualified_name()
        )
        stamp = self._node.get_clock().now().nanoseconds
        self._diagnostics.publish(diagnostics.diagnostic_array(stamp, [status]))
