"""The frame worker without ROS: order, backlog, publish throttling, failures, stop."""

import threading

import numpy as np

from area3d_msgs_py.scheduling import FrameWorker

TIMEOUT_S = 120.0  # generous: every wait ends as soon as its condition holds
K = np.eye(3)


class Recorder:
    """What the worker hands back: fused frames (in order) and failures; fusion can be held."""

    def __init__(self, fused_already=()):
        self.fused, self.done, self.failed = [], [], []
        self.fused_already = set(fused_already)
        self.entered, self.release = threading.Event(), threading.Event()
        self.release.set()
        self.finished = threading.Event()
        self.expected = None

    def fuse(self, stamp, frame, K):
        self.entered.set()
        assert self.release.wait(TIMEOUT_S)
        if frame == "bad":
            raise ValueError("a frame that cannot be fused")
        self.fused.append(stamp)
        return stamp not in self.fused_already

    def on_done(self, stamp, fused, publish_grid):
        self.done.append((stamp, fused, publish_grid))
        if self.expected is not None and len(self.done) + len(self.failed) >= self.expected:
            self.finished.set()
        return True

    def on_failed(self, stamp, exc):
        self.failed.append((stamp, type(exc).__name__))


def worker(recorder, **kwargs):
    return FrameWorker(recorder.fuse, recorder.on_done, recorder.on_failed, "test-worker", **kwargs)


def wait_for(condition) -> bool:
    done = threading.Event()
    for _ in range(int(TIMEOUT_S / 0.01)):
        if condition():
            return True
        done.wait(0.01)
    return condition()


def test_frames_are_fused_in_order_and_the_grid_follows_each_while_fusion_keeps_up():
    rec = Recorder(fused_already={3})
    fusion = worker(rec, now_ns=lambda: 5_000_000_000)
    try:
        for n, stamp in enumerate((1, 2, 3), start=1):
            assert fusion.submit(stamp, "frame", K)
            assert wait_for(lambda n=n: len(rec.done) == n)  # each finds no backlog
    finally:
        fusion.stop(TIMEOUT_S)
    assert rec.fused == [1, 2, 3]
    # 3 had been fused before (a repeat): it changes nothing and publishes no grid
    assert rec.done == [(1, True, True), (2, True, True), (3, False, False)]
    assert fusion.last_done_age_s == (5_000_000_000 - 2) / 1e9  # the last frame really fused
    assert fusion.last_paired_age_s == (5_000_000_000 - 2) / 1e9
    assert fusion.last_process_s is not None and fusion.dropped == 0


def test_while_frames_wait_the_grid_goes_out_once_a_period_and_once_caught_up():
    rec = Recorder()
    rec.release.clear()
    rec.expected = 5
    fusion = worker(rec, publish_period_s=1e6)
    try:
        assert fusion.submit(1, "frame", K)
        assert rec.entered.wait(TIMEOUT_S)  # frame 1 in flight, the next four wait
        for stamp in (2, 3, 4, 5):
            assert fusion.submit(stamp, "frame", K)
        rec.release.set()
        assert rec.finished.wait(TIMEOUT_S)
    finally:
        fusion.stop(TIMEOUT_S)
    grids = [publish for _, _, publish in rec.done]
    # the first grid (none went out yet), none while a backlog waits, the last once caught up
    assert grids == [True, False, False, False, True]


def test_a_full_backlog_drops_the_frame_and_counts_it():
    rec = Recorder()
    rec.release.clear()
    fusion = worker(rec, backlog=2)
    try:
        assert fusion.submit(1, "frame", K)
        assert rec.entered.wait(TIMEOUT_S)  # in flight: the backlog is empty again
        assert fusion.submit(2, "frame", K) and fusion.submit(3, "frame", K)
        assert not fusion.submit(4, "frame", K)
        assert fusion.dropped == 1
        rec.expected = 3
        rec.release.set()
        assert rec.finished.wait(TIMEOUT_S)
    finally:
        fusion.stop(TIMEOUT_S)
    assert rec.fused == [1, 2, 3]


def test_a_frame_whose_fusion_raises_is_reported_and_the_next_is_fused():
    rec = Recorder()
    rec.expected = 2
    fusion = worker(rec)
    try:
        assert fusion.submit(1, "bad", K) and fusion.submit(2, "frame", K)
        assert rec.finished.wait(TIMEOUT_S)
    finally:
        fusion.stop(TIMEOUT_S)
    assert rec.failed == [(1, "ValueError")]
    assert [s for s, *_ in rec.done] == [2]


def test_the_worker_ends_when_the_node_has_stopped_and_on_stop():
    rec = Recorder()
    stopped = threading.Event()

    def on_done(stamp, fused, publish_grid):
        stopped.set()
        return False  # the node's gate is closed

    fusion = FrameWorker(rec.fuse, on_done, rec.on_failed, "test-worker")
    assert fusion.submit(1, "frame", K)
    assert stopped.wait(TIMEOUT_S)
    fusion.stop(TIMEOUT_S)
    assert not fusion.alive
    other = worker(Recorder())
    other.stop(TIMEOUT_S)
    assert not other.alive


def test_cleared_waits_for_the_frame_in_flight_and_drops_those_submitted_before_it():
    rec = Recorder()
    rec.release.clear()
    fusion = worker(rec)
    try:
        assert fusion.submit(1, "frame", K)
        assert rec.entered.wait(TIMEOUT_S)  # frame 1 in flight, 2 and 3 wait
        assert fusion.submit(2, "frame", K) and fusion.submit(3, "frame", K)
        inside = threading.Event()
        found = []

        def clear():
            with fusion.cleared() as waiting:
                found.append((waiting, list(rec.done)))
                inside.set()

        clearing = threading.Thread(target=clear)
        clearing.start()
        assert not inside.wait(0.2)  # it waits for frame 1 to be handed on
        rec.release.set()
        clearing.join(TIMEOUT_S)
        assert inside.is_set()
        rec.expected = 2
        assert fusion.submit(4, "frame", K)  # after the clearing: fused
        assert rec.finished.wait(TIMEOUT_S)
    finally:
        fusion.stop(TIMEOUT_S)
    # frame 1 (and 2 or 3 where the worker took the lock first) was handed on before the body
    # ran; the rest were dropped (not counted as a full backlog's) and none fused after it
    waiting, before = found[0]
    before = [stamp for stamp, *_ in before]
    assert before in ([1], [1, 2], [1, 2, 3])
    assert waiting <= 3 - len(before)  # the worker may hold one off the queue: not fused either
    assert rec.fused == [*before, 4] and fusion.dropped == 0
    assert fusion.last_process_s is not None  # frame 4's


def test_a_stop_asked_before_a_clearing_still_ends_the_worker():
    rec = Recorder()
    rec.release.clear()
    fusion = worker(rec)
    assert fusion.submit(1, "frame", K)
    assert rec.entered.wait(TIMEOUT_S)
    fusion.stop(0.0)  # queued behind frame 1
    rec.release.set()
    with fusion.cleared():
        pass
    assert wait_for(lambda: not fusion.alive)


def test_wait_idle_returns_once_every_submitted_frame_is_processed():
    rec = Recorder()
    rec.release.clear()
    fusion = worker(rec)
    try:
        assert fusion.submit(1, "frame", K) and fusion.submit(2, "frame", K)
        assert rec.entered.wait(TIMEOUT_S)
        assert not fusion.wait_idle(0.05)  # frame 1 in flight, 2 waits
        rec.release.set()
        assert fusion.wait_idle(TIMEOUT_S)
        assert rec.fused == [1, 2] and len(rec.done) == 2
        rec.release.clear()
        assert fusion.submit(3, "frame", K)
        assert rec.entered.wait(TIMEOUT_S)
        with fusion.cleared():  # waits for 3, then nothing is pending
            pass
        assert fusion.wait_idle(0.0)
    finally:
        rec.release.set()
        fusion.stop(TIMEOUT_S)


def test_a_failing_hand_on_ends_the_worker_quietly_only_when_it_is_stopping(monkeypatch):
    """A publish that raises ends the worker (the node then reports it dead), with the thread's
    traceback; while the node stops it ends without one (a Ctrl-C's publish on a shut context)."""
    raised = []
    monkeypatch.setattr(threading, "excepthook", lambda args: raised.append(args.exc_type))

    def on_done(stamp, fused, publish_grid):
        raise RuntimeError("publisher's context is invalid")

    for stopping in (False, True):
        rec = Recorder()
        fusion = FrameWorker(rec.fuse, on_done, rec.on_failed, "test-worker")
        fusion.stopping = stopping
        try:
            assert fusion.submit(1, "frame", K)
            assert wait_for(lambda f=fusion: not f.alive)
            assert fusion.wait_idle(TIMEOUT_S)
        finally:
            fusion.stop(TIMEOUT_S)
        assert rec.failed == []
    assert raised == [RuntimeError]  # the first only


def test_background_steps_are_held_back_by_their_interval_unless_a_caller_waits_for_one():
    """A due step waits for its interval; a caller that waits for a step (urgent) gets it at once,
    one that waits for something else does not start it; close() ends every wait."""
    from area3d_msgs_py.scheduling import BackgroundSteps

    state = {"due": None, "steps": 0}
    stepped = threading.Event()

    def step():
        state["steps"] += 1
        state["due"] = None
        stepped.set()

    steps = BackgroundSteps(lambda: state["due"], step, "test-steps", interval_s=3600.0)
    try:
        state["due"] = "now"  # at once, whatever the interval
        steps.changed()
        assert stepped.wait(TIMEOUT_S) and state["steps"] == 1
        stepped.clear()
        state["due"] = "due"  # the interval (an hour) has not passed since the last step
        steps.changed()
        assert not steps.wait_for(lambda: state["steps"] == 2, 0.3)  # not urgent: held back
        assert steps.wait_for(lambda: state["steps"] == 2, TIMEOUT_S, urgent=True)
        assert steps.alive and steps.tid is not None
    finally:
        steps.close(TIMEOUT_S)
    assert steps.alive  # closed on purpose, not dead
    assert steps.wait_for(lambda: False, TIMEOUT_S, closed=True)  # a closed wait ends at once
