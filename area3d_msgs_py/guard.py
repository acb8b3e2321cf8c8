"""Callbacks that log bad input instead of ending the node.

rclpy lets an exception raised in a callback end ``spin()``, and with it the node; a malformed
message from another process must not do that. ``guarded(node, callback, what)`` logs the error
(an ``InputError`` as one line naming field, value and expectation; anything else with its
traceback) and returns None.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any

from area3d_msgs_py.errors import InputError


def guarded(node: Any, callback: Callable, what: str) -> Callable:
    def call(*args: Any) -> Any:
        try:
            return callback(*args)
        except InputError as exc:
            node.get_logger().warning(f"{what}: rejected: {exc}")
        except Exception:
            node.get_logger().error(f"{what}: exception, input dropped:\n{traceback.format_exc()}")
        return None

    call.__name__ = getattr(callback, "__name__", "callback")
    return call
