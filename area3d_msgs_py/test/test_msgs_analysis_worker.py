"""The semantics node's analysis worker without ROS: one analysis at a time, no request lost."""

import threading

from area3d_msgs_py.scheduling import AnalysisWorker

TIMEOUT_S = 120.0  # generous: every wait ends as soon as its condition holds


class Analyses:
    """Records each analysis; the first one is held until released."""

    def __init__(self):
        self.runs, self.frames = [], [1, 2]
        self.entered, self.release = threading.Event(), threading.Event()
        self.running = 0
        self.overlapped = False
        self.lock = threading.Lock()

    def analyse(self, stamps, reason):
        with self.lock:
            self.running += 1
            self.overlapped |= self.running > 1
        if not self.runs:
            self.entered.set()
            assert self.release.wait(TIMEOUT_S)
        self.runs.append((list(stamps), reason))
        with self.lock:
            self.running -= 1

    def requery(self):
        return list(self.frames)


def test_requests_during_an_analysis_run_once_after_it_with_the_frames_of_then():
    work = Analyses()
    worker = AnalysisWorker(work.analyse, work.requery, "analysis")
    assert worker.submit([1, 2], "initial views")
    assert work.entered.wait(TIMEOUT_S)
    running = worker.running_s  # the status says a query is under way, and since when
    assert running is not None and running >= 0.0
    work.frames.append(3)  # a frame completes while the first query runs
    assert not worker.submit([1, 2, 3], "request") and worker.pending
    assert not worker.submit([1, 2, 3], "request")  # coalesces with the one waiting
    work.release.set()
    assert worker.join(TIMEOUT_S)
    assert work.runs == [([1, 2], "initial views"), ([1, 2, 3], "request")]
    assert not work.overlapped and worker.runs == 2 and not worker.pending
    assert worker.running_s is None


def test_a_request_after_the_analysis_ended_starts_a_new_one():
    work = Analyses()
    work.release.set()
    worker = AnalysisWorker(work.analyse, work.requery, "analysis")
    assert worker.submit([1], "initial views")
    assert worker.join(TIMEOUT_S)
    assert worker.submit([1, 2], "request")
    assert worker.join(TIMEOUT_S)
    assert [reason for _, reason in work.runs] == ["initial views", "request"]


def test_an_analysis_that_raises_frees_the_worker_for_the_next_request():
    calls = []

    def analyse(stamps, reason):
        calls.append(reason)
        if reason == "broken":
            raise RuntimeError("the analysis failed")

    previous = threading.excepthook
    threading.excepthook = lambda args: None  # the thread's traceback is expected here
    try:
        worker = AnalysisWorker(analyse, lambda: [1], "analysis")
        worker.submit([1], "broken")
        assert worker.join(TIMEOUT_S)
        assert (worker.failures, worker.healthy) == (1, False)  # the status says so
        assert worker.submit([1], "request")  # started at once: nothing is stuck
        assert worker.join(TIMEOUT_S)
        assert (worker.failures, worker.healthy) == (1, True)
    finally:
        threading.excepthook = previous
    assert calls == ["broken", "request"]
