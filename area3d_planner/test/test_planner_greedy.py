import numpy as np
import pytest

from area3d_msgs_py.camera_pose import look_rotation
from area3d_msgs_py.grid import GridSpec
from area3d_planner.candidates import VisibilityParams, orientation_bins
from area3d_planner.greedy import (
    GreedyParams,
    lazy_greedy,
    plain_greedy,
    range_gain,
    taken_views,
)
from area3d_planner.visibility import VisibilityCache

SMALL = VisibilityParams(
    level="room", yaw_bins=6, pitch_bins=2, pitch_min_deg=-30, pitch_max_deg=15, face_res=32
)


def random_instance(seed: int, quantised: bool = False):
    rng = np.random.default_rng(seed)
    spec = GridSpec.from_bounds(np.zeros(3), np.full(3, 0.6), 0.05)
    occ = rng.choice(np.array([-1, 0, 1], np.int8), size=spec.num_voxels, p=[0.4, 0.55, 0.05])
    seeds = rng.random((int(rng.integers(5, 25)), 3)) * 0.6
    cache = VisibilityCache.build(spec, occ, seeds, orientation_bins(SMALL)[1], SMALL, threads=1)
    U = rng.random(spec.num_voxels)
    if quantised:  # many exact ties
        U = np.round(U * 2) / 2
    U[occ == 0] = 0
    return cache, U, rng


def test_decay_lowers_exactly_the_committed_views_frustum_by_one_minus_eta():
    cache, U, _ = random_instance(0)
    sel = plain_greedy(cache, U, 1, GreedyParams(eta=0.3))
    ids = cache.frustum(cache.view_pose(sel.views[0]))
    assert set(cache.mask(sel.views[0])[0].tolist()) <= set(ids.tolist())
    changed = np.flatnonzero(sel.field != U)
    np.testing.assert_array_equal(np.sort(changed), np.sort(ids[U[ids] > 0]))
    np.testing.assert_allclose(sel.field[ids], 0.7 * U[ids])
    others = np.setdiff1d(np.arange(U.size), ids)
    np.testing.assert_array_equal(sel.field[others], U[others])


def test_visible_decay_lowers_exactly_the_committed_views_mask_by_one_minus_eta():
    cache, U, _ = random_instance(0)
    sel = plain_greedy(cache, U, 1, GreedyParams(eta=0.3, decay="visible"))
    ids, _ = cache.mask(sel.views[0])
    changed = np.flatnonzero(sel.field != U)
    np.testing.assert_array_equal(np.sort(changed), np.sort(ids[U[ids] > 0]))
    np.testing.assert_allclose(sel.field[ids], 0.7 * U[ids])
    others = np.setdiff1d(np.arange(U.size), ids)
    np.testing.assert_array_equal(sel.field[others], U[others])


def test_the_callers_field_is_not_decayed():
    cache, U, _ = random_instance(1)
    before = U.copy()
    lazy_greedy(cache, U, 3)
    np.testing.assert_array_equal(U, before)


@pytest.mark.parametrize("instance", range(24))
def test_lazy_greedy_returns_exactly_the_plain_greedy_views(instance):
    cache, U, rng = random_instance(instance, quantised=instance % 3 == 0)
    params = GreedyParams(
        decay=str(rng.choice(["frustum", "visible"])),
        eta=float(rng.choice([0.3, 0.0, 1.0, 0.5])),
        w_dist=float(rng.choice([0.0, 0.2])),
        nms_radius=float(rng.choice([0.0, 0.1, 0.3])),
        nms_angle_deg=float(rng.choice([0.0, 30.0, 90.0])),
    )
    start = rng.random(3) * 0.6
    budget = int(rng.integers(1, 15))
    # a range prior (constant per seed) on half of the instances
    gain = range_gain(cache.seeds, rng.random(3), 0.4, 0.5) if instance % 2 else None
    # views already taken are out of the race on a third of the instances
    taken = [cache.view_pose(int(v)) for v in rng.integers(0, cache.num_views, 3)]
    excluded = taken_views(cache, taken, params) if instance % 3 == 1 else None
    plain = plain_greedy(cache, U, budget, params, start, gain, excluded)
    lazy = lazy_greedy(cache, U, budget, params, start, gain, excluded)
    if excluded is not None:
        assert not any(excluded.ravel()[v] for v in lazy.views)
    assert lazy.views == plain.views
    assert lazy.utilities == plain.utilities
    np.testing.assert_array_equal(lazy.field, plain.field)


def test_lazy_greedy_evaluates_far_fewer_views_than_plain_greedy():
    cache, U, _ = random_instance(5)
    cache_big = cache
    plain = plain_greedy(cache_big, U, 10)
    lazy = lazy_greedy(cache_big, U, 10)
    assert lazy.views == plain.views
    assert lazy.evaluations < 0.75 * plain.evaluations


def test_nms_never_commits_the_same_view_twice_and_stops_when_nothing_is_left():
    cache, U, _ = random_instance(2)
    sel = lazy_greedy(
        cache, U, cache.num_views + 5, GreedyParams(nms_radius=0.0, nms_angle_deg=0.0)
    )
    assert len(sel.views) == cache.num_views
    assert len(set(sel.views)) == len(sel.views)


def test_negative_or_nan_fields_are_rejected():
    cache, U, _ = random_instance(3)
    bad = U.copy()
    bad[0] = np.nan
    with pytest.raises(ValueError, match="field"):
        lazy_greedy(cache, bad, 2)
    with pytest.raises(ValueError, match="eta"):
        plain_greedy(cache, U, 2, GreedyParams(eta=1.5))


def test_range_gain_peaks_at_the_working_distance_and_is_off_without_one():
    seeds = np.array([[0.4, 0, 0], [0.2, 0, 0], [1.0, 0, 0], [0, 0.4, 0]])
    gain = range_gain(seeds, np.zeros(3), 0.4, 0.5)
    assert gain[0] == pytest.approx(1.0) and gain[3] == pytest.approx(1.0)
    assert gain[1] < 1 and gain[2] < gain[1]  # 3 sigma too far is worse than 1 sigma too near
    assert range_gain(seeds, np.zeros(3), None, 0.5) is None
    assert range_gain(seeds, np.zeros(3), 0.4, 0.0) is None


def test_views_already_taken_are_the_ones_near_a_captured_pose():
    cache, _, _ = random_instance(4)
    params = GreedyParams(nms_radius=0.05, nms_angle_deg=20.0)
    view = 3 * cache.num_bins + 1
    excluded = taken_views(cache, [cache.view_pose(view)], params)
    assert excluded.ravel()[view]
    s, b = divmod(view, cache.num_bins)
    near = np.linalg.norm(cache.seeds - cache.seeds[s], axis=1) <= 0.05
    for s2, b2 in zip(*np.nonzero(excluded), strict=True):
        assert near[s2]
        angle = np.degrees(np.arccos(np.clip(cache.forward[s2, b2] @ cache.forward[s, b], -1, 1)))
        assert angle <= 20.0 + 1e-9
    assert not taken_views(cache, [], params).any()


def test_a_taken_view_rules_out_the_same_direction_from_the_centre_at_any_range():
    # seeds on two shells around a centre, every one looking at it: a view taken on the inner
    # shell also rules out the outer seed on the same ray, and only seeds within the angle
    spec = GridSpec.from_bounds(np.full(3, -1.0), np.full(3, 1.0), 0.1)
    occ = np.zeros(spec.num_voxels, np.int8)
    centre = np.zeros(3)
    azimuths = np.radians([0.0, 5.0, 30.0, 90.0])
    dirs = np.stack([np.cos(azimuths), np.sin(azimuths), np.zeros(4)], axis=1)
    seeds = np.concatenate([0.4 * dirs, 0.8 * dirs])
    rotations = np.stack([look_rotation(-d) for d in np.concatenate([dirs, dirs])])[:, None]
    cache = VisibilityCache.build(spec, occ, seeds, rotations, SMALL, threads=1)
    taken = [cache.view_pose(0)]  # inner shell, azimuth 0
    params = GreedyParams(nms_radius=0.02, nms_angle_deg=30.0, nms_centre_angle_deg=10.0)
    by_direction = taken_views(cache, taken, params, centre)[:, 0]
    np.testing.assert_array_equal(by_direction, [1, 1, 0, 0, 1, 1, 0, 0])
    # without the centre (or with the angle 0) only the seed itself is ruled out
    only_near = taken_views(cache, taken, params)[:, 0]
    np.testing.assert_array_equal(only_near, [1, 0, 0, 0, 0, 0, 0, 0])
    off = GreedyParams(nms_radius=0.02, nms_angle_deg=30.0)
    np.testing.assert_array_equal(taken_views(cache, taken, off, centre)[:, 0], only_near)


def test_views_taken_from_many_repeated_and_jittered_poses_match_a_direct_count():
    """Repeated poses (a camera streaming from one place) count once; the result is the direct
    pose-by-pose test of distance and angle, with and without the centre rule."""
    cache, _, _ = random_instance(5)
    rng = np.random.default_rng(1)
    places = [cache.view_pose(int(v)) for v in rng.choice(cache.num_views, 6, replace=False)]
    poses = []
    for k in range(600):
        T = places[k % len(places)].copy()
        if k % 3 == 0:  # a third of them moved by up to a few millimetres
            T[:3, 3] += rng.normal(0.0, 0.002, 3)
        poses.append(T)
    centre = cache.seeds.mean(axis=0)
    for params, c in (
        (GreedyParams(nms_radius=0.08, nms_angle_deg=25.0), None),
        (GreedyParams(nms_radius=0.08, nms_angle_deg=25.0, nms_centre_angle_deg=8.0), centre),
    ):
        expected = np.zeros((cache.num_seeds, cache.num_bins), bool)
        for T in poses:
            near = np.linalg.norm(cache.seeds - T[:3, 3], axis=1) <= params.nms_radius
            if c is not None:
                rays = cache.seeds - c
                rays /= np.linalg.norm(rays, axis=1, keepdims=True)
                taken = (T[:3, 3] - c) / np.linalg.norm(T[:3, 3] - c)
                near |= rays @ taken >= np.cos(np.radians(params.nms_centre_angle_deg))
            cos = np.clip(cache.forward @ T[:3, 2], -1.0, 1.0)
            expected |= near[:, None] & (np.degrees(np.arccos(cos)) <= params.nms_angle_deg + 1e-9)
        got = taken_views(cache, poses, params, c)
        assert expected.any() and not expected.all()
        np.testing.assert_array_equal(got, expected)
