"""Whole frames processed one at a time on a thread of the node's own, off its executor: the
scheduling of the nodes (the cores they call are synchronous and own no thread).

A frame's work (the planner's fusion, perception's depth estimate) takes tens of milliseconds or
more; run in a callback it kept the executor busy while the camera's next messages were ready,
and rclpy's multi-threaded executor polls a busy group in a loop that holds the GIL (profiled:
79 % of the planner's GIL time during a 10 Hz soak), and best-effort readers whose queue
overflows meanwhile lose parts for good. The node's callbacks only decode, pair and choose
keyframes; this worker processes, in arrival order.

Backlog: at most `backlog` whole frames wait; a frame that finds them all taken is dropped and
counted, so a camera that outruns the node for good cannot grow its memory without bound.
Publishing: after every processed frame while the worker keeps up; while frames wait at most
every `publish_period_s`, and always once it has caught up (the last state).
No ROS here: the node passes what to do with a processed frame.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

# Whole frames waiting at most (640x480 depth + confidence: 2.4 MB each).
BACKLOG = 128


class FrameWorker:
    """Processes submitted frames with `process(stamp, frame, K) -> bool` (False: the stamp was
    processed already, nothing changed) on a thread named `name`, then calls
    `on_done(stamp, processed, publish) -> bool` (False: the node has stopped, and so does the
    worker). A frame whose processing raises is passed to `on_failed(stamp, exception)` and
    dropped; the frames after it are processed. `now_ns()` is the clock of the frames' stamps
    (the ages below)."""

    def __init__(
        self,
        process: Callable[[int, Any, Any], bool],
        on_done: Callable[[int, bool, bool], bool],
        on_failed: Callable[[int, BaseException], None],
        name: str,
        backlog: int = BACKLOG,
        publish_period_s: float = 1.0,
        now_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._process, self._on_done, self._on_failed = process, on_done, on_failed
        self.name = name
        self.backlog = int(backlog)
        self.publish_period_s = float(publish_period_s)
        self._now_ns = now_ns
        self._queue: queue.Queue = queue.Queue(self.backlog)
        self._published = -np.inf  # time.monotonic() of the last frame that published
        self.dropped = 0  # frames dropped: the backlog was full
        self.last_process_s: float | None = None  # how long the last processed frame took
        # the last processed frame's age when its last part arrived (it was submitted) and once
        # processed, seconds: where a frame's age comes from
        self.last_paired_age_s: float | None = None
        self.last_done_age_s: float | None = None
        self.stopping = False  # stop() was called: the thread ends on purpose
        # held while a frame is processed and handed on, and while `cleared` runs
        self._step = threading.Lock()
        self._generation = 0  # frames submitted before the last `cleared` are not processed
        self._idle = threading.Condition()
        self._pending = 0  # frames submitted and not yet processed or dropped
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    @property
    def waiting(self) -> int:
        """Frames waiting (not counting the one in flight)."""
        return self._queue.qsize()

    def submit(self, stamp_ns: int, frame: Any, K: Any) -> bool:
        """Queue a whole frame; False (and counted in `dropped`) if the backlog is full."""
        with self._idle:
            try:
                self._queue.put_nowait((stamp_ns, frame, K, self._now_ns(), self._generation))
            except queue.Full:
                self.dropped += 1
                return False
            self._pending += 1
            return True

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait until every frame submitted so far is processed (or dropped by `cleared`); True
        if so within `timeout_s`."""
        with self._idle:
            return self._idle.wait_for(lambda: self._pending == 0, timeout_s)

    def _finished(self, frames: int = 1) -> None:
        with self._idle:
            self._pending -= frames
            self._idle.notify_all()

    def stop(self, timeout_s: float) -> None:
        """Stop after the frame in flight (frames still queued are not processed); wait up to
        `timeout_s` for it."""
        self.stopping = True
        if not self._thread.is_alive():
            return
        try:
            self._queue.put(None, timeout=max(timeout_s, 0.1))
        except queue.Full:  # a full backlog: the worker ends at the node's stop anyway
            pass
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    @contextmanager
    def cleared(self) -> Iterator[int]:
        """No frame is processed while the body runs, and none submitted before it after it:
        the frames waiting are dropped (their number is yielded; not counted in `dropped`), the
        one in flight is finished first."""
        with self._step:
            self._generation += 1
            waiting = 0
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is None:  # stop() asked first: it still ends the worker
                    self._queue.put_nowait(None)
                    break
                waiting += 1
            self._finished(waiting)
            self._published = -np.inf
            self.last_process_s = self.last_paired_age_s = self.last_done_age_s = None
            yield waiting

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            with self._step:
                try:
                    if item[4] == self._generation and not self._step_one(*item[:4]):
                        return
                finally:
                    self._finished()

    def _step_one(self, stamp: int, frame: Any, K: Any, submitted_ns: int) -> bool:
        """Process one frame and hand it on; False once the node has stopped."""
        t0 = time.perf_counter()
        try:
            done = self._process(stamp, frame, K)
        except Exception as exc:  # noqa: BLE001 - the frames that follow are processed
            self._on_failed(stamp, exc)
            return True
        publish = False
        if done:
            self.last_process_s = time.perf_counter() - t0
            self.last_paired_age_s = (submitted_ns - stamp) / 1e9
            self.last_done_age_s = (self._now_ns() - stamp) / 1e9
            now = time.monotonic()
            if self._queue.empty() or now - self._published >= self.publish_period_s:
                self._published = now
                publish = True
        try:
            return self._on_done(stamp, done, publish)
        except Exception:
            if self.stopping:  # a stopping node's publish may fail: the worker ends quietly
                return False
            raise  # the thread ends: the node reports its worker dead (`alive`)
