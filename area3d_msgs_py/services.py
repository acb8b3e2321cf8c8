"""Calling a service so that a reply lost to discovery is asked for again.

A client may call as soon as `wait_for_service` says the server is there, while the server has
not yet matched the client's reply reader: Fast DDS then waits 100 ms for that match and drops
the reply if it has not come (seen on a busy 2-core machine, right after a node started). Only a
new request gets an answer then, so `call` sends the request again every `resend_s` until one
is answered: for services a repeat does not harm (a reset, a query), or whose requests carry an
id the server answers a repeat by (the planner's select_views: `request_id`). A closed-loop plan
request without one, repeated, is a new request: the planner takes it for views not captured.
"""

from __future__ import annotations

import threading
import time
from typing import Any

# How long a request waits for its reply before it is sent again: discovery on a loaded machine
# takes seconds, a served request milliseconds (the planner answers a room in under half a second).
RESEND_S = 5.0


def call(client: Any, request: Any, timeout_s: float, resend_s: float = RESEND_S) -> Any:
    """The reply to `request` on the rclpy `client` (its node spun by another thread), sending it
    again every `resend_s` without one; TimeoutError naming the service after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _, d=done: d.set())
        wait = min(resend_s, deadline - time.monotonic())
        if done.wait(max(wait, 0.0)):
            return future.result()
        client.remove_pending_request(future)
        if future.done():  # the reply came as it was given up
            return future.result()
        if time.monotonic() >= deadline:
            raise TimeoutError(f"service {client.service_name}: no reply within {timeout_s:g} s")
