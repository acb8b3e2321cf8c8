"""Whole frames fused one at a time on a thread of the planner's own, off the node's executor.

A frame's fusion takes tens of milliseconds; run in the frames' callback group it kept the group
busy while the camera's next messages were ready, and rclpy's multi-threaded executor polls such
a group in a loop that holds the GIL (profiled: 79 % of the node's GIL time during a 10 Hz soak).
The node's callbacks only decode and pair; this worker fuses, in arrival order.

Backlog: at most `backlog` whole frames wait; a frame that finds them all taken is dropped and
counted, so a camera that outruns the planner for good cannot grow its memory without bound.
Grid: after every fused frame the grid goes out while fusion keeps up; while frames wait for
fusion at most every `grid_period_s`, and always once it has caught up (the last state).
No ROS here: the node passes what to do with a fused frame.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

# Whole frames waiting for fusion at most (640x480 depth + confidence: 2.4 MB each).
FUSION_BACKLOG = 128
WORKER_NAME = "planner-fusion"


class FusionWorker:
    """Fuses submitted frames with `fuse(stamp, frame, K) -> bool` (False: the stamp was fused
    already) on a thread of its own, then calls `on_done(stamp, fused, publish_grid) -> bool`
    (False: the node has stopped, and so does the worker). A frame whose fusion raises is
    passed to `on_failed(stamp, exception)` and dropped; the frames after it are fused.
    `now_ns()` is the clock of the frames' stamps (the ages below)."""

    def __init__(
        self,
        fuse: Callable[[int, Any, np.ndarray], bool],
        on_done: Callable[[int, bool, bool], bool],
        on_failed: Callable[[int, BaseException], None],
        backlog: int = FUSION_BACKLOG,
        grid_period_s: float = 1.0,
        now_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._fuse, self._on_done, self._on_failed = fuse, on_done, on_failed
        self.backlog = int(backlog)
        self.grid_period_s = float(grid_period_s)
        self._now_ns = now_ns
        self._queue: queue.Queue = queue.Queue(self.backlog)
        self._grid_sent = -np.inf  # time.monotonic() of the last frame that published the grid
        self.dropped = 0  # frames dropped: the backlog was full
        self.last_fusion_s: float | None = None  # how long the last fused frame's fusion took
        # the last fused frame's age when its last part arrived (it was submitted) and once
        # fused, seconds: where a frame's age comes from
        self.last_paired_age_s: float | None = None
        self.last_fused_age_s: float | None = None
        self.stopping = False  # stop() was called: the thread ends on purpose
        # held while a frame is fused and handed on, and while `cleared` runs
        self._step = threading.Lock()
        self._generation = 0  # frames submitted before the last `cleared` are not fused
        self._thread = threading.Thread(target=self._loop, name=WORKER_NAME, daemon=True)
        self._thread.start()

    def submit(self, stamp_ns: int, frame: Any, K: np.ndarray) -> bool:
        """Queue a whole frame for fusion; False (and counted in `dropped`) if the backlog is full."""
        try:
            self._queue.put_nowait((stamp_ns, frame, K, self._now_ns(), self._generation))
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def stop(self, timeout_s: float) -> None:
        """Stop after the frame in flight (frames still queued are not fused); wait up to
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
        """No frame is fused while the body runs, and none submitted before it is fused after it:
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
            self._grid_sent = -np.inf
            self.last_fusion_s = self.last_paired_age_s = self.last_fused_age_s = None
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
                if item[4] == self._generation and not self._step_one(*item[:4]):
                    return

    def _step_one(self, stamp: int, frame: Any, K: np.ndarray, submitted_ns: int) -> bool:
        """Fuse one frame and hand it on; False once the node has stopped."""
        t0 = time.perf_counter()
        try:
            fused = self._fuse(stamp, frame, K)
        except Exception as exc:  # noqa: BLE001 - the frames that follow are fused
            self._on_failed(stamp, exc)
            return True
        publish_grid = False
        if fused:
            self.last_fusion_s = time.perf_counter() - t0
            self.last_paired_age_s = (submitted_ns - stamp) / 1e9
            self.last_fused_age_s = (self._now_ns() - stamp) / 1e9
            now = time.monotonic()
            if self._queue.empty() or now - self._grid_sent >= self.grid_period_s:
                self._grid_sent = now
                publish_grid = True
        return self._on_done(stamp, fused, publish_grid)
