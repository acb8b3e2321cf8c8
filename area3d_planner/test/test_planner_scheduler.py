"""The planner's scheduling (`scheduler.PlannerScheduler`): requests that wait for their frame
and for masks that cover it, and the masks rebuilt in the background."""

import os
import threading

import numpy as np
import pytest

from area3d_planner import scheduler as scheduler_module
from area3d_planner.requests import PlanRequest
from area3d_planner.scheduler import PlannerScheduler, SchedulerConfig
from area3d_planner.server import NextBestViewServer
from area3d_planner.test.conftest import closed_loop_config, server_config, wall_frame, wall_frames


def test_request_waits_until_its_stamp_is_fused():
    srv = PlannerScheduler(server_config(), SchedulerConfig(eager_cache=False))
    assert srv.wait_fused(5, timeout_s=0.05) is False
    timer = threading.Timer(0.1, lambda: srv.add_frame(5, *wall_frame()))
    timer.start()
    assert srv.wait_fused(5, timeout_s=120.0) is True  # ends once fused (the first compiles)
    timer.join()


def test_background_refresh_plans_the_same_views_as_a_synchronous_rebuild():
    sync = NextBestViewServer(closed_loop_config())
    eager = PlannerScheduler(closed_loop_config(), SchedulerConfig(refresh_interval_s=0.0))
    try:
        for f in wall_frames():
            sync.add_frame(*f)
            eager.add_frame(*f)
        start = wall_frames()[-1][4]
        for _ in range(3):  # several closed-loop requests, views committed in between
            a, reason_a = sync.plan(PlanRequest(start, 3, 1))
            b, reason_b = eager.plan(PlanRequest(start, 3, 1))
            assert reason_a == reason_b == ""
            np.testing.assert_array_equal(np.array(a), np.array(b))
        assert eager.core.cache_ready() and eager.core.status()["cache_ready"] is True
        assert eager.core.refresh_count >= 1
    finally:
        eager.close()


def test_cache_is_rebuilt_after_frames_without_a_request():
    srv = PlannerScheduler(closed_loop_config(), SchedulerConfig(refresh_interval_s=0.0))
    try:
        assert not srv.core.cache_ready()
        srv.add_frame(*wall_frames()[0])
        assert srv.wait_cache(1, timeout_s=30.0)
        assert srv.core.cache_ready() and srv.core.refresh_count == 1
        assert srv.core.context._caches, "masks were not built eagerly"
    finally:
        srv.close()


def test_frames_arriving_during_a_rebuild_coalesce_into_one_more_rebuild():
    srv = PlannerScheduler(closed_loop_config(), SchedulerConfig(refresh_interval_s=0.0))
    gate = threading.Event()
    started = threading.Event()
    versions = []
    build = srv.core.context.build

    def slow_build(occupancy, kinds=(), evidence=None):
        versions.append(srv.core._map_version)
        started.set()
        gate.wait(30.0)
        return build(occupancy, kinds, evidence)

    srv.core.context.build = slow_build
    try:
        f = wall_frames()
        srv.add_frame(*f[0])
        assert started.wait(30.0)  # the first rebuild is in flight ...
        srv.add_frame(*f[1])  # ... while two more frames arrive
        srv.add_frame(*f[2])
        assert not srv.core.cache_ready()
        gate.set()
        assert srv.wait_cache(3, timeout_s=30.0)
        assert srv.core.refresh_count == 2 and versions == [1, 3]
        assert srv.core.cache_ready()
    finally:
        gate.set()
        srv.close()


def test_a_request_waits_for_the_rebuild_that_covers_its_stamp():
    srv = PlannerScheduler(closed_loop_config(), SchedulerConfig(refresh_interval_s=0.0))
    gate = threading.Event()
    build = srv.core.context.build
    srv.core.context.build = lambda occ, kinds=(), ev=None: (
        gate.wait(30.0) and build(occ, kinds, ev)
    )
    try:
        f = wall_frames()
        srv.add_frame(*f[0])
        result = {}
        t = threading.Thread(
            target=lambda: result.update(plan=srv.plan(PlanRequest(f[0][4], 1, 1)))
        )
        t.start()
        t.join(0.3)
        assert t.is_alive(), "the request did not wait for the masks of its frame"
        gate.set()
        t.join(30.0)
        poses, reason = result["plan"]
        assert reason == "" and len(poses) == 1
    finally:
        gate.set()
        srv.close()


def test_with_a_mask_lag_a_request_plans_from_recent_masks_without_waiting_for_a_rebuild():
    """mask_lag_s: masks built from a map at most that much older (capture time) than the
    request's frame do; an older map still makes the request wait for the rebuild."""
    f = wall_frames()  # stamps 1, 2, 3 ns
    srv = PlannerScheduler(
        closed_loop_config(), SchedulerConfig(refresh_interval_s=0.0, mask_lag_s=1e-9)
    )  # 1 ns
    build = srv.core.context.build
    gate = threading.Event()
    builds = []

    def held_build(occupancy, kinds=()):
        builds.append(srv.core._map_version)
        if len(builds) > 1:
            gate.wait(30.0)  # every rebuild after the first waits for the test
        return build(occupancy, kinds)

    srv.core.context.build = held_build
    try:
        srv.add_frame(*f[0])
        assert srv.wait_cache(1, timeout_s=30.0)
        srv.add_frame(*f[1])  # 1 ns after the masks' newest frame: within the lag
        poses, reason = srv.plan(PlanRequest(f[1][4], 2, 1))
        assert reason == "" and len(poses) == 1
        assert not srv.core.cache_ready()  # planned while the masks lag the map
        assert srv.core.last_plan_s["masks_behind"] == pytest.approx(1e-9)  # by 1 ns, as reported
        srv.add_frame(*f[2])  # 2 ns after it: beyond the lag, the request waits for a rebuild
        assert not srv.wait_cache(3, timeout_s=0.2)
        gate.set()
        assert srv.wait_cache(3, timeout_s=30.0) and srv.core.cache_ready()
        assert srv.core.rebuild_failures == 0  # the rebuilds ran in the worker, not the request
        assert srv.core._previous_masks is None  # streaming: no second set of masks is kept
        assert srv.core._pipeline_base == 0  # nor a map kept for the worker to build first
    finally:
        gate.set()
        srv.close()


def test_pipelined_masks_with_the_background_worker_plan_as_without_it():
    """pipeline_masks with the background worker: a request does not wait for the rebuild of its
    frame, and plans from the masks of the previous request's frame even when the rebuild of
    its own has finished: the views are those planned without the worker, whatever the timing."""
    f = wall_frames()
    piped = server_config(budget=20, mode="closed_loop", pipeline_masks=True)
    srv = PlannerScheduler(piped, SchedulerConfig(refresh_interval_s=0.0))
    sync = NextBestViewServer(piped)
    build = srv.core.context.build
    gate = threading.Event()
    builds = []

    def held_build(occupancy, kinds=()):
        builds.append(srv.core._map_version)
        if len(builds) == 2:
            gate.wait(30.0)  # the rebuild after the second frame waits for the test
        return build(occupancy, kinds)

    srv.core.context.build = held_build
    try:
        answers = []
        for i, x in enumerate(f):
            srv.add_frame(*x)
            sync.add_frame(*x)
            if i == 2:  # the third frame's rebuild finishes before its request
                assert srv.wait_cache(3, timeout_s=30.0) and srv.core.cache_ready()
            a, reason_a = srv.plan(PlanRequest(x[4], x[0], 1))
            b, reason_b = sync.plan(PlanRequest(x[4], x[0], 1))
            assert reason_a == reason_b == ""
            answers.append((a, b, srv.core.last_plan_s["masks_frames_behind"]))
            if i == 1:  # planned while the rebuild of its frame is held
                assert not srv.core.cache_ready()
                gate.set()
        for a, b, _ in answers:
            np.testing.assert_array_equal(np.array(a), np.array(b))
        assert [behind for *_, behind in answers] == [0, 1, 1]
        # the last one planned from the masks of the second frame, which the third's replaced
        assert srv.core.last_plan_s["masks_behind"] == pytest.approx(1e-9)
        assert srv.core.rebuild_failures == 0
    finally:
        gate.set()
        srv.close()


def test_pipelined_masks_are_built_for_the_requests_map_even_when_the_next_frame_came_first():
    """The worker coalesces frames (and starts a rebuild at most every refresh_interval_s unless a
    request waits): when the next frame is fused before it has started on the map of the last
    request's frame, that map is kept and built first, so the next request still plans from it."""
    f = wall_frames()
    piped = server_config(budget=20, mode="closed_loop", pipeline_masks=True)
    srv = PlannerScheduler(piped, SchedulerConfig(refresh_interval_s=3600.0))
    sync = NextBestViewServer(piped)
    try:
        for i, x in enumerate(f):
            srv.add_frame(*x)
            sync.add_frame(*x)
            a, reason_a = srv.plan(PlanRequest(x[4], x[0], 1))
            b, reason_b = sync.plan(PlanRequest(x[4], x[0], 1))
            assert reason_a == reason_b == ""
            np.testing.assert_array_equal(np.array(a), np.array(b))
            assert srv.core.last_plan_s["masks_frames_behind"] == (1 if i else 0)
        assert srv.core.rebuild_failures == 0
    finally:
        srv.close()


def test_the_background_rebuild_runs_at_the_niceness_asked_for():
    srv = PlannerScheduler(
        closed_loop_config(), SchedulerConfig(refresh_interval_s=0.0, rebuild_nice=5)
    )
    try:
        srv.add_frame(*wall_frames()[0])
        assert srv.wait_cache(1, timeout_s=60.0)
        base = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, srv.rebuild.tid) == min(19, base + 5)
        assert base == os.getpriority(os.PRIO_PROCESS, threading.get_native_id())  # only it
    finally:
        srv.close()


def test_a_request_with_the_id_of_one_answered_gets_that_answer_and_is_not_counted_again(
    monkeypatch,
):
    """A repeat of a request (its id) is answered as before; without an id, or with a new one,
    the same closed-loop request from the same frame releases the view handed out and plans
    another. Only the newest `ANSWERS_KEPT` answers are kept."""
    monkeypatch.setattr(scheduler_module, "ANSWERS_KEPT", 2)
    srv = PlannerScheduler(closed_loop_config(), SchedulerConfig(eager_cache=False))
    for f in wall_frames():
        srv.add_frame(*f)
    start = wall_frames()[-1][4]
    first = srv.plan_views(PlanRequest(start, 3, 1, request_id=11))
    assert first.poses and first.reason == ""
    again = srv.plan_views(PlanRequest(start, 3, 1, request_id=11))
    assert again is first and srv.answered(11) is first
    assert srv.core.committed == 1
    other = srv.plan_views(PlanRequest(start, 3, 1, request_id=12))  # a new request, same frame
    assert not np.array_equal(other.poses[0], first.poses[0])
    assert srv.core.committed == 1  # the first view, not captured, was released
    assert srv.answered(0) is None and srv.plan_views(PlanRequest(start, 3, 1)).poses
    srv.plan_views(PlanRequest(start, 3, 1, request_id=13))
    assert srv.answered(11) is None and srv.answered(12) is other  # the oldest forgotten
