"""Executors: one spun on a thread of its own and stopped before it is shut down; executors that
survive a message they cannot take.

rclpy's ``Executor.shutdown`` (Jazzy) destroys the executor's guard condition without waiting for
a ``spin`` in progress on another thread: the spinning thread, woken inside its wait, then reads
the destroyed condition and raises (``'NoneType' object has no attribute 'handle'``). A
``Spinner`` spins until a future of its own is done (rclpy's ``spin_until_future_complete``: the
future's completion wakes the wait and the wait returns; ``Executor.wake`` alone only makes it
wait again). ``stop`` completes the future, joins the thread, waits for the callbacks a
``MultiThreadedExecutor`` handed to its pool (``shutdown`` does not wait for them either), and
only then shuts the executor down, so the nodes can be destroyed after it.

``GuardedExecutor`` and ``GuardedMultiThreadedExecutor`` are rclpy's executors that survive a
message they cannot take. rclpy (Jazzy) builds the Python message inside ``take``; when that
fails (the message class raised while being built), ``take`` raises ("Unable to convert call
argument '0' to Python object") from inside the executor's task, *before* the task marks the
subscription taken and releases its callback group: the exception ends ``spin``, and every later
``spin`` serves neither that subscription nor anything else in its callback group (a node's
default group: all its subscriptions and timers). The node looks alive and does nothing. These
executors drop such a message as a lost one, log it (at most once a second per topic, with the
count), count it per topic (``untaken``; the status line's ``messages_dropped_untaken``) and go
on serving everything; a service request or response that cannot be taken likewise.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import rclpy.logging
from rclpy.executors import (
    Executor,
    ExternalShutdownException,
    MultiThreadedExecutor,
    ShutdownException,
    SingleThreadedExecutor,
)
from rclpy.task import Future

from area3d_msgs_py.guard import Rejections

_UNTAKEN = "untaken"  # the field a message that could not be taken is counted under
_NAMES = {"message": "topic", "request": "service", "response": "service"}


class Spinner:
    """``executor`` spun on a daemon thread named ``name`` until ``stop``."""

    def __init__(self, executor: Executor, name: str = "spin") -> None:
        self.executor = executor
        self._stop = Future()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self.executor.spin_until_future_complete(self._stop)
        except (ExternalShutdownException, ShutdownException):
            pass  # the context was shut down under it (a signal): the spin is over

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout_s: float = 10.0) -> bool:
        """Stop spinning, then shut the executor down; False when a callback was still running
        after ``timeout_s`` (the thread ends after it: the future is read before the next wait)."""
        if not self._stop.done():
            self._stop.set_result(True)  # its done callback wakes the wait
        deadline = time.monotonic() + timeout_s
        self._thread.join(timeout_s)
        # a MultiThreadedExecutor's callbacks handed to its pool and not yet cleaned up
        in_flight = list(getattr(self.executor, "_futures", []))
        while not all(f.done() for f in in_flight) and time.monotonic() < deadline:
            time.sleep(0.005)
        stopped = not self._thread.is_alive() and all(f.done() for f in in_flight)
        self.executor.shutdown()
        return stopped


class _TakeGuard:
    """The executor mixin behind `GuardedExecutor` (see the module's docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # counted per topic, logged at most once a `guard.LOG_PERIOD_S` per topic, as the nodes'
        # rejected inputs are
        self._untaken = Rejections()

    def _take_subscription(self, sub: Any) -> Any:
        try:
            return super()._take_subscription(sub)
        except Exception as exc:
            return self._dropped(sub, sub.topic_name, sub.msg_type, "message", exc)

    def _take_service(self, srv: Any) -> Any:
        try:
            return super()._take_service(srv)
        except Exception as exc:  # the request is lost: its client's call times out
            return self._dropped(srv, srv.service_name, srv.srv_type, "request", exc)

    def _take_client(self, client: Any) -> Any:
        try:
            return super()._take_client(client)
        except Exception as exc:  # the response is lost: the call's future never completes
            return self._dropped(client, client.service_name, client.srv_type, "response", exc)

    def _dropped(self, entity: Any, topic: str, kind: Any, what: str, exc: Exception) -> None:
        """Count and log what could not be taken; None: no callback, so the executor's task
        marks the entity taken and frees its callback group. While the context shuts down,
        what rclpy does then, unchanged."""
        if not self.context.ok():
            raise exc
        unlogged = self._untaken.to_log(topic, _UNTAKEN)
        self._untaken.count(topic, _UNTAKEN)
        if unlogged is None:
            return None
        count = self.untaken()[topic]
        since = f"; {unlogged} more not logged since" if unlogged else ""
        name = getattr(kind, "__name__", str(kind))
        cause = exc.__cause__ or exc.__context__
        why = f"{type(exc).__name__}: {exc}" + (
            "" if cause is None else f", from {type(cause).__name__}: {cause}"
        )
        self._logger_of(entity).warning(
            f"{topic}: a {name} {what} could not be taken ({why}); "
            f"dropped as a lost {what} ({count} on this {_NAMES[what]} so far{since})"
        )
        return None

    def _logger_of(self, entity: Any) -> Any:
        for node in self.get_nodes():
            if any(entity in group for group in (node.subscriptions, node.services, node.clients)):
                return node.get_logger()
        return rclpy.logging.get_logger("executor")

    def untaken(self) -> dict[str, int]:
        """Messages, requests and responses dropped because they could not be taken, per topic or
        service (JSON-ready)."""
        return self._untaken.snapshot()["by_topic"]


class GuardedExecutor(_TakeGuard, SingleThreadedExecutor):
    """rclpy's `SingleThreadedExecutor`, surviving a message it cannot take."""


class GuardedMultiThreadedExecutor(_TakeGuard, MultiThreadedExecutor):
    """rclpy's `MultiThreadedExecutor`, surviving a message it cannot take."""
