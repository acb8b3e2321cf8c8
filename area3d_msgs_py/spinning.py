"""An executor spun on a thread of its own that is stopped before the executor is shut down.

rclpy's ``Executor.shutdown`` (Jazzy) destroys the executor's guard condition without waiting for
a ``spin`` in progress on another thread: the spinning thread, woken inside its wait, then reads
the destroyed condition and raises (``'NoneType' object has no attribute 'handle'``). A
``Spinner`` spins until a future of its own is done (rclpy's ``spin_until_future_complete``: the
future's completion wakes the wait and the wait returns; ``Executor.wake`` alone only makes it
wait again). ``stop`` completes the future, joins the thread, waits for the callbacks a
``MultiThreadedExecutor`` handed to its pool (``shutdown`` does not wait for them either), and
only then shuts the executor down, so the nodes can be destroyed after it.
"""

from __future__ import annotations

import threading
import time

from rclpy.executors import Executor, ExternalShutdownException, ShutdownException
from rclpy.task import Future


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
