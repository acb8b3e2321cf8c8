import threading

import numpy as np

from area3d_planner.server import NextBestViewServer, PlannerConfig, PlanRequest
from area3d_planner.visibility import look_at

K = np.array([[32.0, 0, 32], [0, 32.0, 24], [0, 0, 1]])


def config(**kw):
    base = dict(
        workspace_min=(0.0, 0.0, 0.0),
        workspace_max=(1.0, 1.0, 1.0),
        roi_min=(0.3, 0.0, 0.0),
        roi_max=(1.0, 1.0, 1.0),
        voxel_size=0.05,
        seed_spacing=0.2,
        yaw_bins=6,
        pitch_bins=2,
        mc_rays=32,
        budget=20,
        mode="closed_loop",
    )
    base.update(kw)
    return PlannerConfig(**base)


def frames():
    """Three frames from different places, each seeing a wall at another depth."""
    out = []
    for i, (y, d) in enumerate([(0.5, 0.525), (0.3, 0.6), (0.7, 0.45)]):
        T = look_at(np.array([0.1, y, 0.5]), np.array([1.0, y, 0.5]))
        depth = np.full((48, 64), d, np.float32)
        out.append((i + 1, depth, np.full_like(depth, 0.6 + 0.1 * i), K, T))
    return out


def test_background_refresh_plans_the_same_views_as_a_synchronous_rebuild():
    sync = NextBestViewServer(config())
    eager = NextBestViewServer(config(), background=True)
    try:
        for f in frames():
            sync.add_frame(*f)
            eager.add_frame(*f)
        start = frames()[-1][4]
        for _ in range(3):  # several closed-loop requests, views committed in between
            a, reason_a = sync.plan(PlanRequest(start, 3, 1))
            b, reason_b = eager.plan(PlanRequest(start, 3, 1))
            assert reason_a == reason_b == ""
            np.testing.assert_array_equal(np.array(a), np.array(b))
        assert eager.cache_ready() and eager.status()["cache_ready"] is True
        assert eager.refresh_count >= 1
    finally:
        eager.close()


def test_cache_is_rebuilt_after_frames_without_a_request():
    srv = NextBestViewServer(config(), background=True)
    try:
        assert not srv.cache_ready()
        srv.add_frame(*frames()[0])
        assert srv.wait_cache(1, timeout_s=30.0)
        assert srv.cache_ready() and srv.refresh_count == 1
        assert srv.context._caches, "masks were not built eagerly"
    finally:
        srv.close()


def test_frames_arriving_during_a_rebuild_coalesce_into_one_more_rebuild():
    srv = NextBestViewServer(config(), background=True)
    gate = threading.Event()
    started = threading.Event()
    versions = []
    build = srv.context.build

    def slow_build(occupancy, kinds=()):
        versions.append(srv._map_version)
        started.set()
        gate.wait(30.0)
        return build(occupancy, kinds)

    srv.context.build = slow_build
    try:
        f = frames()
        srv.add_frame(*f[0])
        assert started.wait(30.0)  # the first rebuild is in flight ...
        srv.add_frame(*f[1])  # ... while two more frames arrive
        srv.add_frame(*f[2])
        assert not srv.cache_ready()
        gate.set()
        assert srv.wait_cache(3, timeout_s=30.0)
        assert srv.refresh_count == 2 and versions == [1, 3]
        assert srv.cache_ready()
    finally:
        gate.set()
        srv.close()


def test_a_request_waits_for_the_rebuild_that_covers_its_stamp():
    srv = NextBestViewServer(config(), background=True)
    gate = threading.Event()
    build = srv.context.build
    srv.context.build = lambda occ, kinds=(): gate.wait(30.0) and build(occ, kinds)
    try:
        f = frames()
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
