import threading

import numpy as np
import pytest

from area3d_msgs_py.errors import InputError
from area3d_planner.requests import PlanRequest, get_plan_request
from area3d_planner.server import NextBestViewServer
from area3d_planner.test.conftest import (
    closed_loop_config,
    server_config,
    wall_frame,
    wall_frames,
)


def test_request_before_any_frame_gives_an_empty_plan_with_a_reason():
    poses, reason = NextBestViewServer(server_config()).plan(PlanRequest(None))
    assert poses == [] and "no frame" in reason


def test_batch_request_for_zero_views_plans_the_remaining_budget_then_reports_it_spent():
    srv = NextBestViewServer(server_config(budget=6))
    srv.add_frame(1, *wall_frame())
    poses, reason = srv.plan(PlanRequest(wall_frame()[3], 1, 0))
    assert reason == "" and len(poses) == 5  # 6 in total, 1 captured
    for T in poses:
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)
        assert np.all(T[:3, 3] >= 0) and np.all(T[:3, 3] <= 1)
    poses, reason = srv.plan(PlanRequest(None, 1, 1))
    assert poses == [] and "budget" in reason


def test_closed_loop_counts_captured_and_committed_views_against_the_budget():
    srv = NextBestViewServer(server_config(budget=4, mode="closed_loop"))
    srv.add_frame(1, *wall_frame())
    poses, _ = srv.plan(PlanRequest(None, 1, 0))
    assert len(poses) == 1 and srv.remaining_budget() == 2
    srv.add_frame(2, *wall_frame())  # the planned view was captured: still 2 left
    assert srv.remaining_budget() == 2
    poses, reason = srv.plan(PlanRequest(None, 2, 3))
    assert poses == [] and reason == "count: got 3, expected at most the remaining budget 2"
    # the field as the caller's message names it: NextBestView's count, GetPlan's goal x
    poses, reason = srv.plan(get_plan_request(None, 2, 3.0))
    assert reason.startswith("goal.pose.position.x: got 3, expected at most")
    with pytest.raises(InputError, match="goal.pose.position.x: got 2.7"):
        get_plan_request(None, 2, 2.7)
    with pytest.raises(InputError, match="goal.pose.position.x: got -1"):
        get_plan_request(None, 2, -1.0)


def test_more_views_than_candidates_and_nan_uncertainty_give_empty_plans():
    srv = NextBestViewServer(server_config(budget=10_000))
    srv.add_frame(1, *wall_frame())
    poses, reason = srv.plan(PlanRequest(None, 1, 5000))
    assert poses == [] and "candidate" in reason
    srv.grid.conf_sum[3] = np.nan
    poses, reason = srv.plan(PlanRequest(None, 1, 1))
    assert poses == [] and "NaN" in reason
    srv.grid.conf_sum[3] = 0
    assert srv.plan(PlanRequest(None, 1, 1))[0]  # and the server keeps serving


def test_workspace_without_a_valid_seed_gives_an_empty_plan():
    # workspace entirely inside unobserved space: no known-free position for a camera
    srv = NextBestViewServer(
        server_config(workspace_min=(0.8, 0.8, 0.8), workspace_max=(0.95, 0.95, 0.95))
    )
    srv.add_frame(1, *wall_frame())
    poses, reason = srv.plan(PlanRequest(None, 1, 1))
    assert poses == [] and "workspace" in reason


def test_degenerate_configuration_is_rejected_naming_the_field():
    with pytest.raises(InputError, match="workspace"):
        NextBestViewServer(server_config(workspace_min=(0, 0, 1), workspace_max=(1, 1, 1)))
    with pytest.raises(InputError, match="policy"):
        NextBestViewServer(server_config(policy="best"))
    with pytest.raises(InputError, match="mode"):
        NextBestViewServer(server_config(mode="online"))


def test_semantic_map_arriving_before_its_frame_is_fused_when_the_frame_arrives():
    srv = NextBestViewServer(server_config())
    depth, conf, K_, T = wall_frame()
    assert srv.add_semantic(7, np.full_like(depth, 0.5)) is False
    assert srv.grid.semantic_frames == 0
    srv.add_frame(7, depth, conf, K_, T)
    assert srv.grid.semantic_frames == 1 and srv.grid.semantic().max() == pytest.approx(0.5)
    assert srv.add_semantic(7, np.full_like(depth, 0.5)) is True


@pytest.mark.parametrize("policy", ["area3d", "volumetric_ig", "vlm_naive", "random", "uniform"])
def test_every_policy_returns_the_requested_number_of_valid_poses(policy):
    srv = NextBestViewServer(server_config(policy=policy, budget=10))
    srv.add_frame(1, *wall_frame())
    poses, reason = srv.plan(PlanRequest(None, 1, 3))
    assert reason == "" and len(poses) == 3
    for T in poses:
        assert np.all(T[:3, 3] >= 0) and np.all(T[:3, 3] <= 1)
        np.testing.assert_allclose(np.linalg.det(T[:3, :3]), 1.0, atol=1e-9)


@pytest.mark.parametrize("policy", ["uniform", "random"])
def test_field_independent_policies_continue_their_sequence_in_closed_loop(policy):
    batch = NextBestViewServer(server_config(budget=5, policy=policy, mode="batch"))
    batch.add_frame(1, *wall_frame())
    planned, _ = batch.plan(PlanRequest(None, 1, 0))
    loop = NextBestViewServer(server_config(budget=5, policy=policy, mode="closed_loop"))
    loop.add_frame(1, *wall_frame())
    handed_out = []
    for stamp in range(2, 6):
        poses, reason = loop.plan(PlanRequest(None, stamp - 1, 1))
        assert reason == "" and len(poses) == 1
        handed_out.append(poses[0])
        loop.add_frame(stamp, *wall_frame())
    assert len(planned) == 4
    for a, b in zip(planned, handed_out, strict=True):
        np.testing.assert_allclose(a, b)  # the same sequence, one view per request
    positions = np.array([T[:3, 3] for T in handed_out])
    assert len({tuple(np.round(p, 6)) for p in positions}) == 4, "a view was handed out twice"


def test_uniform_views_keep_the_working_distance_of_the_captured_frames():
    roomy = dict(workspace_min=(-1.0, -1.0, 0.0), workspace_max=(2.0, 2.0, 2.0))
    srv = NextBestViewServer(server_config(budget=8, policy="uniform", level="object", **roomy))
    srv.add_frame(1, *wall_frame())
    poses, _ = srv.plan(PlanRequest(None, 1, 0))
    centre = np.array([0.65, 0.5, 0.5])  # ROI centre
    working = np.linalg.norm(wall_frame()[3][:3, 3] - centre)
    distances = [np.linalg.norm(T[:3, 3] - centre) for T in poses]
    assert np.median(distances) == pytest.approx(working, rel=0.25)


def test_a_committed_view_is_turned_to_centre_the_uncertainty_it_sees():
    from area3d_planner.policies import aim_at_uncertainty

    srv = NextBestViewServer(server_config(budget=6))
    srv.add_frame(1, *wall_frame())
    cache = srv.context.cache()
    view = next(v for v in range(cache.num_views) if cache.mask(v)[0].size > 10)
    ids, _ = cache.mask(view)
    U = np.zeros(cache.spec.num_voxels)
    hot = ids[len(ids) // 3]
    U[hot] = 1.0  # one uncertain voxel in view: the camera must end up looking straight at it
    T = aim_at_uncertainty(cache, view, U)
    centre = (
        cache.spec.lower
        + (np.array(np.unravel_index(hot, cache.spec.shape)) + 0.5) * cache.spec.voxel_size
    )
    axis = (centre - T[:3, 3]) / np.linalg.norm(centre - T[:3, 3])
    np.testing.assert_allclose(T[:3, 2], axis, atol=1e-9)
    np.testing.assert_allclose(T[:3, 3], cache.view_pose(view)[:3, 3])  # position unchanged
    np.testing.assert_allclose(
        aim_at_uncertainty(cache, view, np.zeros_like(U)), cache.view_pose(view)
    )


def test_closed_loop_requests_remember_the_decay_of_views_already_committed():
    srv = NextBestViewServer(server_config(budget=6, mode="closed_loop", eta=0.3))
    srv.add_frame(1, *wall_frame())
    first, _ = srv.plan(PlanRequest(None, 1, 1))
    cache = srv.context.cache()
    decay = srv.context.committed_decay
    assert decay is not None and np.isclose(decay.min(), 0.7) and decay.max() == 1.0
    # the decayed voxels are exactly those inside the frustum of the pose sent to the camera
    committed = np.flatnonzero(decay < 1.0)
    np.testing.assert_array_equal(committed, np.sort(cache.frustum(first[0])))
    # with no new frame, the next request does not send the camera back to the same view
    second, _ = srv.plan(PlanRequest(None, 1, 1))
    assert not np.allclose(first[0], second[0])


def test_the_grid_keeps_within_its_voxel_budget_and_puts_box_faces_mid_voxel():
    big = server_config(
        workspace_min=(-3.0, -2.0, 0.0),
        workspace_max=(3.0, 2.0, 2.5),
        roi_min=(-3.0, -2.0, 0.0),
        roi_max=(3.0, 2.0, 2.5),
        voxel_size=0.0,
        voxel_budget=200_000,
        level="auto",
    )
    spec = big.grid_spec()
    assert spec.num_voxels <= 200_000
    assert big.resolved_level() == "room" and spec.voxel_size > 0.05  # coarser than the level's
    small = server_config(voxel_size=0.0, level="object", roi_min=(0.3, 0.0, 0.73))
    spec = small.grid_spec()
    assert spec.voxel_size == 0.01  # object level default fits the budget
    # a support plane at the ROI's floor (a table top at z = 0.73) lies mid-voxel
    k = (0.73 - spec.lower[2]) / spec.voxel_size
    assert abs(k - np.floor(k) - 0.5) < 1e-6


def test_level_is_room_when_the_camera_works_inside_the_region():
    inside = server_config(
        level="auto",
        workspace_min=(0.1, 0.1, 0.1),
        workspace_max=(0.9, 0.9, 0.9),
        roi_min=(0, 0, 0),
    )
    around = server_config(level="auto", workspace_min=(-1, -1, 0), workspace_max=(2, 2, 2))
    assert inside.resolved_level() == "room" and around.resolved_level() == "object"
    with pytest.raises(InputError, match="level"):
        NextBestViewServer(server_config(level="galaxy"))


def test_a_newer_semantic_map_of_a_frame_replaces_the_older_one():
    srv = NextBestViewServer(server_config())
    depth, conf, K_, T = wall_frame()
    srv.add_frame(7, depth, conf, K_, T)
    assert srv.add_semantic(7, np.full_like(depth, 0.2))
    assert srv.add_semantic(7, np.full_like(depth, 0.6))  # a re-query's newer analysis
    s = srv.grid.semantic()
    assert srv.grid.semantic_frames == 1
    np.testing.assert_allclose(s[s > 0], 0.6, rtol=1e-5)
    # a map of another frame is averaged in as before
    srv.add_frame(8, depth, conf, K_, T)
    assert srv.add_semantic(8, np.full_like(depth, 0.2))
    s = srv.grid.semantic()
    assert srv.grid.semantic_frames == 2
    np.testing.assert_allclose(s[s > 0], 0.4, rtol=1e-5)


def test_a_frame_replayed_with_the_same_stamp_is_fused_once():
    """After a restart every saved frame is replayed; the ones the planner has must not count twice."""
    server = NextBestViewServer(server_config())
    assert server.add_frame(5, *wall_frame()) is True
    grid_after_one = (server.grid.conf_sum.copy(), server.grid.frames)
    assert server.add_frame(5, *wall_frame()) is False
    np.testing.assert_array_equal(server.grid.conf_sum, grid_after_one[0])
    assert server.grid.frames == grid_after_one[1] == 1
    assert server.status()["frames_fused"] == 1
    assert server.add_frame(6, *wall_frame()) is True and server.grid.frames == 2


def _masks(server):
    cache = server.context._caches["roi_not_free"]
    return cache.seeds, cache.indptr, cache.voxel_ids, cache.weights


def test_pipelined_masks_plan_each_request_from_the_masks_of_the_previous_requests_frame():
    """pipeline_masks without the background worker: the first closed-loop request plans from
    masks of its frame; each next one from the masks of the map at the previous request's frame,
    exactly as built from that map, leaving out the positions its own frame shows too close to
    geometry; a batch request gets masks that cover every frame."""
    f = wall_frames()
    piped = NextBestViewServer(server_config(budget=20, mode="closed_loop", pipeline_masks=True))
    exact = NextBestViewServer(server_config(budget=20, mode="closed_loop", pipeline_masks=False))
    masks_of = []  # the exact masks after each frame
    for i, x in enumerate(f):
        piped.add_frame(*x)
        exact.add_frame(*x)
        poses, reason = piped.plan(PlanRequest(x[4], x[0], 1))
        assert reason == "" and len(poses) == 1
        assert exact.plan(PlanRequest(x[4], x[0], 1))[1] == ""
        masks_of.append([a.copy() for a in _masks(exact)])
        assert piped.last_plan_s["masks_frames_behind"] == (1 if i else 0)
        if i:  # the masks it planned from: those of the map at the previous request's frame
            for a, b in zip(_masks(piped), masks_of[i - 1], strict=True):
                np.testing.assert_array_equal(a, b)
    # the positions the third frame shows too close to geometry are the ones left out
    seeds = piped.context.seeds()
    blocked = ~piped.context.valid_positions(seeds, piped.grid.occupancy())
    assert blocked.any() and not blocked.all()
    np.testing.assert_array_equal(piped.context.blocked_seeds, blocked)
    chosen = poses[0][:3, 3]
    assert not np.any(np.all(np.isclose(seeds[blocked], chosen), axis=1))
    # a batch request does not plan from them
    assert piped.plan(PlanRequest(f[2][4], 3, 1, mode="batch"))[1] == ""
    assert piped.last_plan_s["masks_frames_behind"] == 0 and piped.context.blocked_seeds is None
    for a, b in zip(_masks(piped), masks_of[2], strict=True):
        np.testing.assert_array_equal(a, b)


def test_selection_never_takes_a_view_from_a_blocked_position():
    srv = NextBestViewServer(closed_loop_config())
    for x in wall_frames():
        srv.add_frame(*x)
    srv.plan(PlanRequest(None, 3, 1))  # builds the masks
    context, policy = srv.context, srv.policy
    context.committed_decay = None
    bins = context.candidates()[1].shape[1]
    first = policy.selection(context, 1).views[0] // bins
    context.blocked_seeds = np.zeros(context.seeds().shape[0], bool)
    context.blocked_seeds[first] = True
    second = policy.selection(context, 3).views
    assert second and all(v // bins != first for v in second)


def test_frames_are_fused_while_a_plan_selects_its_views():
    """The selection runs on a snapshot outside the map's lock: a frame arriving meanwhile is
    fused at once, and the plan's committed decay is kept afterwards."""
    f = wall_frames()
    srv = NextBestViewServer(closed_loop_config())
    srv.add_frame(*f[0])
    select = srv.policy.select_views
    selecting, release = threading.Event(), threading.Event()

    def held_select(context, budget):
        selecting.set()
        release.wait(30.0)
        return select(context, budget)

    srv.policy.select_views = held_select
    answers = []
    planner = threading.Thread(target=lambda: answers.append(srv.plan(PlanRequest(None, 1, 1))))
    planner.start()
    try:
        assert selecting.wait(30.0)
        fused = []
        fuser = threading.Thread(target=lambda: fused.append(srv.add_frame(*f[1])))
        fuser.start()
        fuser.join(30.0)
        assert fused == [True] and srv.grid.frames == 2  # while the selection is held
        assert planner.is_alive() and srv.context.committed_decay is None
    finally:
        release.set()
        planner.join(30.0)
    ((poses, reason),) = answers
    assert reason == "" and len(poses) == 1 and srv.committed == 1
    decay = srv.context.committed_decay
    assert decay is not None and np.isclose(decay.min(), 0.7)


def test_a_plan_carries_the_greedy_utility_of_each_view_without_changing_the_views():
    """Gains are the utilities the greedy selection committed the views with (best first), and
    asking for them chooses the same views as a plan without them."""
    with_gains, without = NextBestViewServer(server_config()), NextBestViewServer(server_config())
    for srv in (with_gains, without):
        srv.add_frame(1, *wall_frame())
    start = wall_frame()[3]
    expected = with_gains.policy.selection(with_gains.context, 3)
    assert isinstance(expected.utilities[0], float)
    plan = with_gains.plan_views(PlanRequest(start, 1, 3))
    poses, reason = without.plan(PlanRequest(start, 1, 3))
    assert plan.reason == reason == "" and len(plan.poses) == len(plan.gains) == 3
    np.testing.assert_array_equal(np.array(plan.poses), np.array(poses))
    assert plan.gains == expected.utilities  # the selection on the same map and candidates
    assert plan.gains[0] > 0 and plan.gains == sorted(plan.gains, reverse=True)


@pytest.mark.parametrize("policy", ["uniform", "random"])
def test_policies_without_a_gain_model_report_zero_gains(policy):
    srv = NextBestViewServer(server_config(policy=policy, budget=10))
    srv.add_frame(1, *wall_frame())
    plan = srv.plan_views(PlanRequest(None, 1, 2))
    assert plan.reason == "" and plan.gains == [0.0, 0.0]


def test_a_request_may_name_its_mode_and_a_bad_one_is_refused_by_name():
    srv = NextBestViewServer(server_config(budget=6, mode="batch"))
    srv.add_frame(1, *wall_frame())
    plan = srv.plan_views(PlanRequest(None, 1, 0, mode="closed_loop"))
    assert plan.reason == "" and len(plan.poses) == 1  # closed loop: one view for count 0
    plan = srv.plan_views(PlanRequest(None, 1, 0, mode="sideways"))
    assert plan.poses == [] and plan.reason.startswith("mode: got 'sideways'")
    plan = srv.plan_views(PlanRequest(None, 1, 0))
    assert plan.reason == "" and len(plan.poses) == 4  # the planner's batch: the rest


def test_candidate_views_take_the_camera_of_the_fused_frames():
    """The frustum and resolution come from the frames' intrinsics (any size and field of view);
    a camera equal to the parameters changes nothing."""
    srv = NextBestViewServer(server_config(width=64, height=48, hfov_deg=90.0))
    visibility = srv.context.visibility
    srv.add_frame(1, *wall_frame())  # fx 32 over 64 pixels, 90 degrees: the parameters' camera
    assert srv.context.visibility is visibility and srv.camera() == (90.0, 64, 48)
    wide = np.array([[424 / np.tan(np.radians(43.5)), 0, 424], [0, 400.0, 240], [0, 0, 1]])
    depth = np.full((480, 848), 0.525, np.float32)
    srv.add_frame(2, depth, np.full_like(depth, 0.8), wide, wall_frame()[3])
    hfov, width, height = srv.camera()
    assert (width, height) == (848, 480) and hfov == pytest.approx(87.0, abs=1e-9)
    v = srv.context.visibility
    assert v.tan_y == pytest.approx(np.tan(np.radians(43.5)) * 480 / 848)  # fy taken as fx
    poses, reason = srv.plan(PlanRequest(None, 2, 1))
    assert reason == "" and len(poses) == 1
    assert srv.context.cache().params.hfov_deg == pytest.approx(87.0)


def test_a_closed_loop_view_the_camera_did_not_capture_stops_counting_against_the_budget():
    srv = NextBestViewServer(server_config(budget=3, mode="closed_loop"))
    srv.add_frame(1, *wall_frame())
    first, _ = srv.plan(PlanRequest(None, 1, 1))
    assert len(first) == 1 and srv.remaining_budget() == 1
    # asked again from the same frame, nothing fused since: the first view was never captured
    second, reason = srv.plan(PlanRequest(None, 1, 1))
    assert reason == "" and len(second) == 1 and srv.remaining_budget() == 1
    srv.add_frame(2, *wall_frame())  # this one was captured
    third, reason = srv.plan(PlanRequest(None, 2, 1))
    assert reason == "" and len(third) == 1 and srv.remaining_budget() == 0
    srv.add_frame(3, *wall_frame())
    assert srv.plan(PlanRequest(None, 3, 1)) == (
        [],
        "budget: all 3 views are spent (1 initial, 2 handed out)",
    )


def _moved(T, dx):
    U = np.array(T, float)
    U[:3, 3] += [0.0, dx, 0.0]
    return U


def test_frames_streamed_between_views_are_fused_but_never_spend_the_budget():
    """A streaming camera: 12 frames fused before the first request count as the level's |O_0|
    at most (initial_views 4 here), and the 30 streamed while the robot drives to each view
    count nothing: only the views handed out do."""
    srv = NextBestViewServer(server_config(budget=7, mode="closed_loop", initial_views=4))
    depth, conf, K_, T = wall_frame()
    stamp = 0
    for i in range(12):
        stamp += 1
        srv.add_frame(stamp, depth, conf, K_, _moved(T, 0.02 * i))
    assert srv.remaining_budget() == 3 and srv.status()["budget"]["initial"] == 4
    for view in range(3):
        poses, reason = srv.plan(PlanRequest(None, stamp, 1))
        assert reason == "" and len(poses) == 1, reason
        for _ in range(30):  # the drive there, streamed
            stamp += 1
            srv.add_frame(stamp, depth, conf, K_, poses[0])
        assert srv.remaining_budget() == 2 - view
    assert srv.grid.frames == 12 + 90
    budget = srv.status()["budget"]
    assert budget == {"views": 7, "initial": 4, "handed_out": 3, "spent": 7}
    _, reason = srv.plan(PlanRequest(None, stamp, 1))
    assert reason == "budget: all 7 views are spent (4 initial, 3 handed out)"
    # one frame per view (initial_views 0: the level's 15 at most): every frame before the
    # first request counts, as before
    triggered = NextBestViewServer(server_config(budget=6))
    triggered.add_frame(1, depth, conf, K_, T)
    triggered.add_frame(2, depth, conf, K_, _moved(T, 0.1))
    assert triggered.remaining_budget() == 4


def test_with_keyframes_a_skipped_frame_is_covered_by_a_newer_one_or_one_from_near_its_pose():
    from area3d_msgs_py.keyframes import KeyframeConfig

    near = KeyframeConfig(0.1, 10.0, 1.0).near
    srv = NextBestViewServer(server_config())
    depth, conf, K_, T = wall_frame()
    srv.add_frame(10, depth, conf, K_, T)
    assert srv.covers(10) and srv.covers(0) and not srv.covers(11)
    # stamp 11 was skipped (the camera had not moved): the map holds its view
    assert srv.covers(11, _moved(T, 0.05), near) and not srv.covers(11, _moved(T, 0.3), near)
    assert not srv.covers(12, _moved(T, 0.3), near)
    srv.add_frame(13, depth, conf, K_, _moved(T, 0.5))  # a newer frame holds what 12 saw
    assert srv.covers(12, _moved(T, 0.3), near)
    note = srv.stale_note(20 * 10**9, 5.0)
    assert note.startswith(f"frame {20 * 10**9} not fused within 5 s: planned from the map up to")
    assert "frame 13, 20.00 s older" in note


def test_a_view_handed_out_again_says_so_and_whether_a_frame_from_there_was_fused():
    srv = NextBestViewServer(server_config(budget=10, mode="closed_loop"))
    srv.add_frame(1, *wall_frame())
    first = srv.plan_views(PlanRequest(None, 1, 1))
    assert first.reason == "" and first.note == ""
    (view,) = first.poses
    # the same view chosen again (the frame from it lost on the way) is said to repeat
    assert srv._repeats([view]) == (
        "view 0 was handed out before (view 0 of this map): no frame from there has been fused since"
    )
    assert srv._repeats([_moved(view, 0.5)]) == ""  # elsewhere: nothing to say
    depth, conf, K_, _ = wall_frame()
    srv.add_frame(2, depth, conf, K_, view)  # now a frame from there was fused
    assert "a frame from there was fused (stamp 2)" in srv._repeats([view])


def test_no_candidate_view_is_placed_nearer_to_geometry_than_the_cameras_minimum_range():
    srv = NextBestViewServer(server_config(min_range=0.3, budget=20))
    srv.add_frame(1, *wall_frame())  # a wall at x = 0.625
    poses, reason = srv.plan(PlanRequest(None, 1, 3))
    assert reason == "" and len(poses) == 3
    occupied = srv.grid.spec.centers_of(np.flatnonzero(srv.grid.occupancy() == 1))
    seeds = srv.context.seeds()
    half_diagonal = np.sqrt(3) / 2 * srv.grid.spec.voxel_size
    for at in [*seeds, *(T[:3, 3] for T in poses)]:
        assert np.linalg.norm(occupied - at, axis=1).min() >= 0.3 - half_diagonal
    assert srv.context.visibility.near == 0.3  # nothing nearer counts as seen
    near = NextBestViewServer(server_config(budget=20))
    near.add_frame(1, *wall_frame())
    assert near.context.seeds().shape[0] > seeds.shape[0]  # the limit left seeds out
    with pytest.raises(InputError, match="^min_range: "):
        NextBestViewServer(server_config(min_range=6.0))


def test_a_view_turned_to_its_uncertainty_never_repeats_a_view_already_taken():
    """One uncertain voxel the best view sees far off its orientation bin: turned to it, that
    view faces where a taken view faced, although its bin lies beyond the NMS angle of it (so
    the candidates' NMS keeps it). The planner leaves it out and sends another view."""
    from area3d_planner.greedy import near_taken, taken_views
    from area3d_planner.policies import GreedyFieldPolicy, aim_at_uncertainty

    srv = NextBestViewServer(server_config(budget=6, mode="closed_loop"))
    srv.add_frame(1, *wall_frame())
    context = srv.context
    cache = context.cache(GreedyFieldPolicy.relevant)

    class OneVoxel(GreedyFieldPolicy):
        name = "one_voxel"

        def __init__(self, voxel):
            self.voxel = voxel

        def field(self, context):
            U = np.zeros(context.grid.spec.num_voxels)
            U[self.voxel] = 1.0
            return U

    found = None
    for voxel in np.unique(np.concatenate([cache.mask(v)[0] for v in range(cache.num_views)])):
        policy = OneVoxel(int(voxel))
        context.camera_poses = context.camera_poses[:1]  # the frame's own pose only
        context._fields.clear()
        U = context.policy_field(policy)
        first = policy.selection(context, 1, U).views
        if not first:
            continue
        aimed = aim_at_uncertainty(cache, first[0], U)
        bin_off = np.degrees(
            np.arccos(np.clip(aimed[:3, 2] @ cache.view_pose(first[0])[:3, 2], -1, 1))
        )
        if bin_off > context.greedy.nms_angle_deg + 1.0:
            found = (policy, aimed, first[0])
            break
    assert found is not None, "no view whose aim leaves its bin beyond the NMS angle"
    policy, aimed, view = found
    context.camera_poses = context.camera_poses + [aimed]  # the camera went there
    # the candidates' NMS alone keeps the view: it would be sent again
    assert not taken_views(cache, context.camera_poses, context.greedy).reshape(-1)[view]
    chosen = policy.select_views(context, 1).poses
    assert len(chosen) == 1
    assert not near_taken(chosen[0], context.camera_poses, context.greedy)
