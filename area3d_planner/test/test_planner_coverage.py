"""Coverage views (`coverage_below`): once the best view's gain falls below a share of the first
planned view's, the view taken is, of the views whose gain is near the best one's, the one whose
direction from the region centre is farthest from every captured camera's."""

import dataclasses

import numpy as np
import pytest

from area3d_msgs_py.camera_pose import look_at
from area3d_planner.config import PlannerConfig
from area3d_planner.policies import (
    COVERAGE_KEEP,
    excluded_views,
    gains_collapsed,
    make_policy,
)
from area3d_planner.test.conftest import set_occupancy

CENTRE = np.array([0.0, 0.0, 0.8])


def object_context(coverage_below: float = 0.5, level: str = "object"):
    """A planning context around a 20 cm region: a block of unknown space in it (what no frame
    saw), the rest of the region carved free, and two views captured from one side."""
    config = PlannerConfig(
        level=level,
        workspace_min=(-2.0, -2.0, 0.0),
        workspace_max=(2.0, 2.0, 2.0),
        roi_min=(-0.1, -0.1, 0.7),
        roi_max=(0.1, 0.1, 0.9),
        voxel_size=0.02,
        coverage_below=coverage_below,
    )
    grid = config.fused_grid()
    context = config.planning_context(grid)
    centres = grid.spec.centers_of(np.arange(grid.spec.num_voxels))
    occ = np.where(grid.roi_mask, 0, -1).astype(np.int8)
    occ[np.all(np.abs(centres - CENTRE) <= 0.05, axis=1)] = -1
    set_occupancy(grid, occ)
    for azimuth in (0.0, 0.4):
        position = CENTRE + 0.6 * np.array([np.cos(azimuth), np.sin(azimuth), 0.5])
        T = look_at(position, CENTRE)
        context.camera_poses.append(T)
        context.camera_positions.append(T[:3, 3].copy())
    context.initial_views = 2
    return context


def least_angles(points: np.ndarray, taken: np.ndarray) -> np.ndarray:
    """(P,) least angle (radians) between each point's direction from the centre and the taken
    ones'."""
    a = points - CENTRE
    b = taken - CENTRE
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    return np.arccos(np.clip(a @ b.T, -1, 1)).min(axis=1)


def test_the_first_plan_sets_the_reference_and_keeps_the_greedys_view():
    context = object_context()
    plain = dataclasses.replace(
        context, greedy=dataclasses.replace(context.greedy, coverage_below=0)
    )
    policy = make_policy("area3d")
    views = policy.select_views(context, 1)
    assert context.first_gain == pytest.approx(views.gains[0]) and views.gains[0] > 0
    np.testing.assert_array_equal(views.poses[0], policy.select_views(plain, 1).poses[0])
    assert plain.first_gain is None  # off: nothing is kept


def collapsed(context):
    """`context` after its first plan, with the reference set ten times its best gain now."""
    policy = make_policy("area3d")
    policy.select_views(context, 1)
    best = policy.selection(context, 1)
    context.first_gain = 10.0 * best.utilities[0]
    return policy, best


def test_once_the_gains_collapse_the_view_is_the_least_seen_direction_among_near_equals():
    context = object_context()
    policy, best = collapsed(context)
    cache = context.cache("roi_not_free")
    U = context.policy_field(policy)
    scores = cache.score(U)
    allowed = (scores >= COVERAGE_KEEP * best.utilities[0]) & ~excluded_views(
        context, cache
    ).reshape(-1)
    taken = np.array([T[:3, 3] for T in context.camera_poses])
    angles = np.repeat(least_angles(cache.seeds, taken), cache.num_bins)
    views = policy.select_views(context, 1)
    T = views.poses[0]
    seed = int(np.argmin(np.linalg.norm(cache.seeds - T[:3, 3], axis=1)))
    np.testing.assert_allclose(cache.seeds[seed], T[:3, 3])
    view = seed * cache.num_bins + int(
        np.argmin(np.abs(scores[seed * cache.num_bins :][: cache.num_bins] - views.gains[0]))
    )
    assert allowed[view] and views.gains[0] == pytest.approx(scores[view])
    assert angles[view] >= angles[allowed].max() - 1e-9  # no allowed view is farther
    # ... and it is not the greedy's view, which looks from a direction seen more closely
    assert angles[view] > angles[best.views[0]] + 0.1
    assert views.gains[0] < best.utilities[0]
    assert (
        views.note.startswith("coverage view: the best gain") and "coverage_below=0.5" in views.note
    )


def test_a_blocked_seed_is_never_taken_for_coverage():
    context = object_context()
    policy, _ = collapsed(context)
    cache = context.cache("roi_not_free")
    first = policy.select_views(dataclasses.replace(context), 1).poses[0][:3, 3]
    blocked = np.all(np.isclose(cache.seeds, first), axis=1)
    assert blocked.sum() == 1
    context.blocked_seeds = blocked
    second = policy.select_views(context, 1).poses[0][:3, 3]
    assert not np.allclose(second, first)


@pytest.mark.parametrize(("share", "budget"), [(0.0, 1), (0.5, 2)])
def test_off_or_for_several_views_at_once_every_view_is_the_greedys(share, budget):
    context = object_context(share)
    policy, _ = collapsed(context)
    greedy = policy.selection(dataclasses.replace(context), budget)
    views = policy.select_views(context, budget)
    assert views.gains == pytest.approx(greedy.utilities) and len(views.gains) == budget
    assert views.note == ""


def test_at_room_level_the_gains_never_collapse():
    context = object_context(0.5, level="room")
    context.first_gain = 1e9
    assert not gains_collapsed(context, 1.0)
    context = object_context(0.5)
    assert not gains_collapsed(context, 10.0) and context.first_gain == 10.0  # the first plan
    assert not gains_collapsed(context, 5.0) and gains_collapsed(context, 4.9)


def test_thousands_of_streamed_frames_choose_as_the_places_they_were_taken_from(monkeypatch):
    # a streaming camera fuses a frame at every step of its path: the captured directions are
    # compared in blocks, and a camera's repeated frames change nothing
    import area3d_planner.policies as policies

    monkeypatch.setattr(policies, "DIRECTION_BLOCK", 3)
    few, many = object_context(), object_context()
    many.camera_poses = [T for T in many.camera_poses for _ in range(5)]
    many.camera_positions = [T[:3, 3].copy() for T in many.camera_poses]
    chosen = []
    for context in (few, many):
        policy, _ = collapsed(context)
        chosen.append(policy.select_views(context, 1).poses[0])
    np.testing.assert_array_equal(chosen[0], chosen[1])
