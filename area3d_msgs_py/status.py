"""A node's status line: JSON in std_msgs/String on area3d/<node>/status (`topics.*_STATUS`).

Published a moment after something changed (a frame processed, an input rejected), so a barrage of
bad messages yields one status line after it rather than one per message, and, where the node
asks for one, once a period as a heartbeat, so `ros2 topic echo` shows the counters of a quiet
node too. A node's worker threads publish with `publish()` (inside the node's `PublishGate`).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from area3d_msgs_py import msgs
from area3d_msgs_py.topics import Topic

CHANGE_DELAY_S = 0.05  # a burst of changes within this time yields one status line
HEARTBEAT_S = 1.0


class StatusPublisher:
    """Publishes `state()` as JSON on `topic` shortly after `changed()` and, unless `heartbeat_s`
    is None, every `heartbeat_s` seconds."""

    def __init__(
        self,
        node: Any,
        topic: Topic,
        state: Callable[[], dict],
        heartbeat_s: float | None = HEARTBEAT_S,
    ) -> None:
        self._state = state
        self._pub = node.create_publisher(msgs.String, topic.name, topic.qos())
        self._soon = node.create_timer(CHANGE_DELAY_S, self._publish_soon)
        self._soon.cancel()
        if heartbeat_s is not None:
            node.create_timer(heartbeat_s, self.publish)

    def changed(self) -> None:
        """Something in the state changed: publish it shortly (repeated calls coalesce)."""
        self._soon.reset()

    def _publish_soon(self) -> None:
        self._soon.cancel()
        self.publish()

    def publish(self) -> None:
        """Publish the state now."""
        self._pub.publish(msgs.String(data=json.dumps(self._state())))
