"""The scheduling of the nodes: every thread, queue, priority and wait around the cores they
call, which are synchronous and own no thread. No ROS here: a node passes what to run.

- `FrameWorker`: whole frames processed one at a time on a thread of the node's own, off its
  executor (the planner's fusion, perception's depth estimate, the reconstruction's integration).
- `AnalysisWorker`: long analyses (a VLM query: seconds to minutes) one at a time, requests that
  arrive meanwhile coalesced into one more (the semantics node).
- `StateWaits` and `BackgroundSteps`: callers that wait on a core's state, and a core's upkeep
  (the planner's mask rebuilds) stepped on a thread of its own, at a lower CPU priority if asked.

FrameWorker:

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

import os
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


class AnalysisWorker:
    """Runs `analyse(stamps, reason)` on a worker thread, one analysis at a time.

    A request that arrives while an analysis runs is not lost: it runs next, in the same worker,
    on the frames `requery()` names at that moment (every frame complete by then); requests that
    arrive during one analysis coalesce into that one next run.
    """

    def __init__(
        self,
        analyse: Callable[[list[int], str], None],
        requery: Callable[[], list[int]],
        name: str,
    ) -> None:
        self._analyse = analyse
        self._requery = requery
        self._name = name
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._pending = False
        self.runs = 0  # analyses finished
        self.failures = 0  # analyses that raised (each ended its thread)
        self.healthy = True  # False from an analysis that raised until one finishes
        self._started: float | None = None  # time.monotonic() the running analysis began

    @property
    def running_s(self) -> float | None:
        """How long the running analysis has run, seconds (None: none runs)."""
        with self._lock:
            started = self._started
        return None if started is None else time.monotonic() - started

    @property
    def busy(self) -> bool:
        """An analysis is running (or about to)."""
        with self._lock:
            return self._thread is not None

    @property
    def pending(self) -> bool:
        """A request waits for the running analysis to end."""
        with self._lock:
            return self._pending

    def submit(self, stamps: list[int], reason: str) -> bool:
        """Analyse `stamps` now (True), or, while an analysis runs, the frames of `requery()`
        right after it (False)."""
        with self._lock:
            if self._thread is not None:
                self._pending = True
                return False
            self._thread = threading.Thread(
                target=self._run, args=(list(stamps), reason), name=self._name, daemon=True
            )
            self._thread.start()
            return True

    def join(self, timeout_s: float | None = None) -> bool:
        """Wait until no analysis runs or is pending; True if none does."""
        with self._lock:
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
        return not self.busy

    def _run(self, stamps: list[int], reason: str) -> None:
        while True:
            finished = False
            with self._lock:
                self._started = time.monotonic()
            try:
                self._analyse(stamps, reason)
                finished = True
            finally:  # an analysis that raised ends the worker; the next submit starts a new one
                with self._lock:
                    self._started = None
                    self.runs += 1
                    self.failures += not finished
                    self.healthy = finished
                    again = finished and self._pending
                    self._pending = False
                    if not again:
                        self._thread = None
            if not again:
                return
            stamps, reason = self._requery(), "request"


class StateWaits:
    """Callers that wait for a core's state to reach something (`wait_for`), woken by whoever
    changes it (`changed`). `close()` ends every wait at once (a stopping node)."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self.waiting = 0  # callers in `wait_for(urgent=True)` now
        self.closed = False

    def changed(self) -> None:
        with self._changed:
            self._changed.notify_all()

    def wait_for(
        self,
        predicate: Callable[[], bool],
        timeout_s: float | None,
        closed: bool = False,
        urgent: bool = False,
    ) -> bool:
        """Block until `predicate()` holds, or `timeout_s` passes, or `close()`; the predicate's
        last value, or `closed` once closed. `urgent`: the wait is for a background step, which
        then runs at once (`BackgroundSteps`: not held back by its interval)."""
        with self._changed:
            self.waiting += urgent
            self._changed.notify_all()  # a background step may be holding back: one waits
            try:
                held = self._changed.wait_for(lambda: self.closed or predicate(), timeout_s)
            finally:
                self.waiting -= urgent
            if self.closed:
                return closed or bool(predicate())
            return bool(held)

    def close(self) -> None:
        with self._changed:
            self.closed = True
            self._changed.notify_all()


class BackgroundSteps(StateWaits):
    """A core's upkeep run one step at a time on a thread named `name`, and the waits on the state
    it changes.

    `due()` says what is to do: "now" (a step at once), "due" (a step once `interval_s` has
    passed since the last one started, or at once while a caller waits in `wait_for(urgent=True)`)
    or None
    (nothing: the thread sleeps until `changed()`). `step()` runs one; `after()` is called after
    each (what it raises is ignored: a listener must not stop the upkeep); `warm_up()` runs once
    first, on the thread. With `nice` > 0 the thread runs that much nicer than the process (Linux:
    a thread's own nice value, which the threads it starts inherit). An exception a step raises
    ends the thread (`alive` turns False) unless `close()` was called meanwhile."""

    def __init__(
        self,
        due: Callable[[], str | None],
        step: Callable[[], Any],
        name: str,
        interval_s: float = 0.0,
        nice: int = 0,
        warm_up: Callable[[], Any] | None = None,
        after: Callable[[], Any] | None = None,
    ) -> None:
        super().__init__()
        self._due, self._step, self._warm_up, self._after = due, step, warm_up, after
        self.interval_s = float(interval_s)
        self.nice = int(nice)
        self.tid: int | None = None  # the thread's id (Linux), once it runs
        self._last = -np.inf  # time.monotonic() at the start of the last step
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def alive(self) -> bool:
        """The thread runs, or was stopped by `close` (False: it died)."""
        return self._thread.is_alive() or self.closed

    def close(self, timeout_s: float | None = None) -> None:
        """Stop: a step in flight finishes first, or is left to die with the process after
        `timeout_s` (the thread is a daemon)."""
        super().close()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def _run(self) -> None:
        try:
            self._steps()
        except Exception:
            if not self.closed:
                raise

    def _steps(self) -> None:
        self.tid = threading.get_native_id()
        if self.nice > 0:
            base = os.getpriority(os.PRIO_PROCESS, self.tid)
            os.setpriority(os.PRIO_PROCESS, self.tid, min(19, base + self.nice))
        if self._warm_up is not None:
            self._warm_up()
        while True:
            with self._changed:
                while not self.closed:
                    due = self._due()
                    if due == "now":
                        break
                    wait_s = self._last + self.interval_s - time.monotonic()
                    if due == "due" and (wait_s <= 0 or self.waiting > 0):
                        break
                    self._changed.wait(wait_s if due == "due" else None)
                if self.closed:
                    return
                self._last = time.monotonic()
            self._step()
            self.changed()
            if self._after is not None:
                try:
                    self._after()
                except Exception:  # noqa: BLE001 - a failing listener must not stop the upkeep
                    pass
