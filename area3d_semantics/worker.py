"""Region analyses run one at a time on a thread of their own (a VLM query takes seconds to
minutes), so the semantics node's callbacks keep taking frames meanwhile. No ROS here."""

from __future__ import annotations

import threading
from collections.abc import Callable

WORKER_NAME = "semantics-vlm"


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
        name: str = WORKER_NAME,
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
            try:
                self._analyse(stamps, reason)
                finished = True
            finally:  # an analysis that raised ends the worker; the next submit starts a new one
                with self._lock:
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
