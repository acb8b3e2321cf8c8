import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from area3d_msgs_py.camera_pose import look_at
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec
from area3d_planner.cloud import CLOUD_DTYPE, grid_to_cloud
from area3d_planner.fusion import FusedGrid

K = np.array([[32.0, 0, 32], [0, 32.0, 24], [0, 0, 1]])  # 64x48 image, 90 degree hfov


def wall_frame():
    """Camera at x = 0.1 looking along +x at a wall at x = 0.625 (mid-voxel)."""
    T = look_at(np.array([0.1, 0.5, 0.5]), np.array([1.0, 0.5, 0.5]))
    depth = np.full((48, 64), 0.525, np.float32)
    return depth, T


def make_grid(**kw):
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    return FusedGrid(spec, np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0]), **kw)


def at(grid, point):
    return grid.spec.flat_index(np.asarray([point]))[0][0]


def test_depth_frame_marks_wall_occupied_space_before_it_free_and_behind_it_unknown():
    grid = make_grid(gamma=0.01)
    depth, T = wall_frame()
    grid.integrate_depth(depth, np.full_like(depth, 0.75), K, T, max_range=5.0, stride=1)
    occ = grid.occupancy()
    assert occ[at(grid, [0.62, 0.5, 0.5])] == 1
    assert occ[at(grid, [0.35, 0.5, 0.5])] == 0
    assert occ[at(grid, [0.85, 0.5, 0.5])] == -1
    geo = grid.geometric()
    assert geo[at(grid, [0.62, 0.5, 0.5])] == pytest.approx(0.25)
    assert geo[at(grid, [0.35, 0.5, 0.5])] == 0.0
    assert geo[at(grid, [0.85, 0.5, 0.5])] == 1.0


def test_pixels_declared_without_a_return_carve_to_max_range_and_pixels_without_an_estimate_never():
    """REP 117: +Inf (no return within range: open space, sky) carves free space out to
    max_range; NaN (no estimate: a dropout, a failed stereo match) carves nothing, however large
    the region, and the rays that did hit the wall still carve up to it."""
    depth, T = wall_frame()
    depth[:, :32] = np.inf  # the image's left half (world +y) saw nothing within range
    grid = make_grid(gamma=0.01)
    grid.integrate_depth(depth, np.ones_like(depth), K, T, max_range=5.0, stride=1)
    occ = grid.occupancy()
    assert occ[at(grid, [0.9, 0.9, 0.5])] == 0
    assert occ[at(grid, [0.9, 0.1, 0.5])] == -1  # behind the wall on the other side
    depth[:, :32] = np.nan  # the same half without an estimate
    grid = make_grid(gamma=0.01)
    grid.integrate_depth(depth, np.ones_like(depth), K, T, max_range=5.0, stride=1)
    occ = grid.occupancy()
    assert occ[at(grid, [0.9, 0.9, 0.5])] == -1 and occ[at(grid, [0.35, 0.8, 0.5])] == -1
    assert occ[at(grid, [0.35, 0.3, 0.5])] == 0  # carved along the rays that hit the wall
    assert not np.any(occ[grid.spec.centers()[:, 0] > 0.65] == 0)  # nothing behind the wall


def test_a_depth_at_confidence_zero_marks_its_voxel_but_carves_nothing_in_front_of_it():
    """A stereo match the left-right check refused keeps its depth at confidence 0: the voxel it
    lands in is a hit as uncertain as one can be, but the space in front of it is not known
    free; +Inf at confidence 0 (no return within range) still carves."""
    depth, T = wall_frame()
    conf = np.full_like(depth, 0.75)
    conf[:, :32] = 0.0  # the image's left half (world +y): refused matches on the wall
    grid = make_grid(gamma=0.01)
    grid.integrate_depth(depth, conf, K, T, max_range=5.0, stride=1)
    occ = grid.occupancy()
    assert occ[at(grid, [0.62, 0.8, 0.5])] == 1  # the guessed wall is still a hit ...
    assert grid.geometric()[at(grid, [0.62, 0.8, 0.5])] == 1.0  # ... at confidence 0
    assert occ[at(grid, [0.5, 0.8, 0.5])] == -1  # nothing in front of it carved
    assert occ[at(grid, [0.5, 0.2, 0.5])] == 0  # the confident half carves as before
    assert occ[at(grid, [0.62, 0.2, 0.5])] == 1
    depth[:, :32] = np.inf  # the same half declared without a return, at confidence 0
    grid = make_grid(gamma=0.01)
    grid.integrate_depth(depth, conf, K, T, max_range=5.0, stride=1)
    assert grid.occupancy()[at(grid, [0.9, 0.9, 0.5])] == 0


def test_a_depth_below_carve_min_confidence_is_a_hit_at_its_confidence_that_carves_nothing():
    """`carve_min_confidence`: a depth less trusted than this is a hit at its own confidence but
    no evidence of free space in front of it; at or above it, it carves; +Inf always carves."""
    depth, T = wall_frame()
    conf = np.full_like(depth, 0.75)
    conf[:, :32] = 0.5  # the image's left half (world +y)
    depth[:4, :32] = np.inf  # a band declared without a return, at the low confidence
    for threshold, carved in ((0.6, False), (0.5, True), (0.0, True)):
        grid = make_grid(gamma=0.01, carve_min_confidence=threshold)
        grid.integrate_depth(depth, conf, K, T, max_range=5.0, stride=1)
        occ = grid.occupancy()
        assert occ[at(grid, [0.62, 0.8, 0.5])] == 1
        assert grid.geometric()[at(grid, [0.62, 0.8, 0.5])] == pytest.approx(0.5)
        assert occ[at(grid, [0.5, 0.8, 0.5])] == (0 if carved else -1), threshold
        assert occ[at(grid, [0.5, 0.2, 0.5])] == 0  # the more confident half carves
        assert occ[at(grid, [0.7, 0.8, 0.92])] == 0  # +Inf carves out to max_range
    with pytest.raises(InputError, match="carve_min_confidence"):
        make_grid(gamma=0.01, carve_min_confidence=1.5)


def test_a_frame_without_any_return_within_range_carves_to_max_range_only():
    grid = make_grid(gamma=0.01)
    depth, T = wall_frame()
    depth[:] = np.inf
    grid.integrate_depth(depth, np.ones_like(depth), K, T, max_range=0.6, stride=1)
    occ = grid.occupancy()
    assert occ[at(grid, [0.45, 0.5, 0.5])] == 0
    assert occ[at(grid, [0.9, 0.5, 0.5])] == -1  # beyond z = 0.6 m from the camera
    assert not np.any(occ == 1)


@pytest.mark.parametrize("gain_rule", ["removable", "held"])
def test_fused_adds_gamma_to_every_non_free_roi_voxel_and_is_zero_outside_the_roi(gain_rule):
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    grid = FusedGrid(
        spec,
        np.array([0.0, 0.0, 0.0]),
        np.array([1.0, 1.0, 0.5]),
        gamma=0.01,
        gain_rule=gain_rule,
    )
    depth, T = wall_frame()
    grid.integrate_depth(depth, np.full_like(depth, 0.75), K, T, stride=1)
    u, occ, geo = grid.fused(), grid.occupancy(), grid.geometric()
    inside = grid.roi_mask
    non_free = occ != 0
    share = grid.achievability() if gain_rule == "removable" else 1.0
    expected = (geo * share + 0.01)[inside & non_free]
    np.testing.assert_allclose(u[inside & non_free], expected, rtol=1e-6)
    assert np.all(u[inside & ~non_free] == 0)
    assert np.all(u[~inside] == 0)
    assert inside.any() and (~inside).any()
    wall = at(grid, [0.62, 0.5, 0.4])
    if gain_rule == "removable":  # seen once with 0.75: 0.75 + 0.25 x 0.25 of its G can still go
        assert u[wall] == pytest.approx(0.25 * 0.8125 + 0.01)


def _view_of_wall_from(angle_deg: float):
    """The wall frame's camera turned about the wall point (0.625, 0.5, 0.5) by `angle_deg` in
    the horizontal plane, with the depth of the plane x = 0.625 in that view."""
    target = np.array([0.625, 0.5, 0.5])
    a = np.radians(angle_deg)
    eye = target - 0.525 * np.array([np.cos(a), np.sin(a), 0.0])
    T = look_at(eye, target)
    v, u = np.mgrid[0:48, 0:64]
    rays = np.stack([(u + 0.5 - 32) / 32, (v + 0.5 - 24) / 32, np.ones((48, 64))], -1)
    world = rays @ T[:3, :3].T
    t = (0.625 - eye[0]) / world[..., 0]  # distance along each ray to the plane, as optical z
    return np.where(t > 0, t, np.nan).astype(np.float32), T


def test_a_surface_no_direction_resolves_stops_attracting_and_is_reported_hard():
    grid = make_grid(gamma=0.0)
    wall = at(grid, [0.62, 0.5, 0.5])
    shares, hard = [], []
    for angle in (0.0, 50.0, -50.0):  # three distinct directions (bins about 45 degrees wide)
        depth, T = _view_of_wall_from(angle)
        grid.integrate_depth(depth, np.full_like(depth, 0.2), K, T, stride=1)
        shares.append(grid.achievability()[wall])
        hard.append(bool(grid.hard()[wall]))
    assert grid.direction_count()[wall] == 3
    # c* + (1 - c*) r^n with c* = 0.2, r = retry_gain (1/4): hope falls with every direction
    # that did no better
    r = grid.retry_gain
    assert r == 0.25
    np.testing.assert_allclose(
        shares, [0.2 + 0.8 * r, 0.2 + 0.8 * r**2, 0.2 + 0.8 * r**3], rtol=1e-5
    )
    assert hard == [False, False, True]
    assert grid.fused()[wall] == pytest.approx(grid.geometric()[wall] * shares[-1], rel=1e-5)
    # the same three views with a confident backend: nothing is hard, little is left to remove
    sure = make_grid(gamma=0.0)
    for angle in (0.0, 50.0, -50.0):
        depth, T = _view_of_wall_from(angle)
        sure.integrate_depth(depth, np.full_like(depth, 0.9), K, T, stride=1)
    assert not sure.hard()[wall] and sure.achievability()[wall] > 0.9


def test_the_range_profile_is_the_backends_mean_confidence_by_range_relative_to_its_best():
    grid = make_grid(gamma=0.0)
    assert np.all(grid.range_profile()[0] == 1.0)  # nothing seen yet: no preference
    T = look_at(np.array([0.02, 0.5, 0.5]), np.array([1.0, 0.5, 0.5]))
    depth = np.full((48, 64), 0.3, np.float32)  # a near wall in the left half of the image ...
    depth[:, 32:] = 0.9  # ... and a far one in the right half
    conf = np.where(depth < 0.5, 0.8, 0.2).astype(np.float32)
    grid.integrate_depth(depth, conf, K, T, stride=1)
    profile, width = grid.range_profile()
    near, far = profile[int(0.3 / width)], profile[int(0.9 / width)]
    assert near == pytest.approx(1.0) and far == pytest.approx(0.25, rel=0.05)
    assert profile[-1] == pytest.approx(far)  # beyond the last bin seen: its value


def test_voxels_in_view_without_any_return_lose_attraction_after_several_directions():
    grid = make_grid(gamma=0.0)
    glossy = at(grid, [0.62, 0.5, 0.5])
    for n, angle in enumerate((0.0, 50.0, -50.0), start=1):
        depth, T = _view_of_wall_from(angle)
        depth[20:28, 28:36] = np.nan  # the middle of the wall returns nothing (a mirror, glass)
        grid.integrate_depth(depth, np.ones_like(depth), K, T, stride=1)
        assert grid.occupancy()[glossy] == -1  # neither hit nor carved: still unknown
        assert grid.achievability()[glossy] == pytest.approx(0.25**n)
    assert grid.hard()[glossy]
    assert grid.fused()[glossy] == pytest.approx(0.25**3)  # unobserved uncertainty 1 x 1/64
    # a voxel the camera never looked at keeps its full share
    assert grid.achievability()[at(grid, [0.9, 0.9, 0.9])] == 1.0
    with pytest.raises(InputError, match="gain_rule"):
        make_grid(gamma=0.0, gain_rule="hope")


def test_a_voxel_behind_a_surface_whose_pixel_dropped_out_was_not_looked_at():
    # a depth camera's dropouts on a surface seen at an angle: single pixels without a return
    # among pixels that hit it. The voxels behind the wall at those pixels are hidden by it, not
    # looked at: they keep their full share and are never reported hard
    grid = make_grid(gamma=0.0)
    behind = [at(grid, [x, y, 0.5]) for x in (0.72, 0.77, 0.82) for y in (0.42, 0.5, 0.58)]
    glossy = at(grid, [0.62, 0.5, 0.5])
    for angle in (0.0, 50.0, -50.0):
        depth, T = _view_of_wall_from(angle)
        depth[::2, ::2] = np.nan  # one pixel in four drops out
        depth[1::2, 1::2] = np.nan
        grid.integrate_depth(depth, np.ones_like(depth), K, T, stride=1)
    assert np.all(grid.occupancy()[behind] == -1)  # neither hit nor carved: unknown
    assert np.all(grid.direction_count()[behind] == 0)
    assert np.all(grid.achievability()[behind] == 1.0) and not grid.hard()[behind].any()
    assert grid.occupancy()[glossy] == 1  # the wall itself: hit where its pixels returned
    # a hole of no return over the wall's middle is still looked at: its voxels lose attraction
    hole = make_grid(gamma=0.0)
    for angle in (0.0, 50.0, -50.0):
        depth, T = _view_of_wall_from(angle)
        depth[16:32, 24:40] = np.nan
        hole.integrate_depth(depth, np.ones_like(depth), K, T, stride=1)
    assert hole.direction_count()[glossy] == 3 and hole.hard()[glossy]


def test_gamma_zero_ablation_leaves_unobserved_uncertainty_only():
    grid = make_grid(gamma=0.0)
    depth, T = wall_frame()
    grid.integrate_depth(depth, np.ones_like(depth), K, T, stride=1)
    u = grid.fused()
    # a full-confidence surface: one observation lowers it to 1 - max_confidence, no gamma
    assert u[at(grid, [0.62, 0.5, 0.5])] == pytest.approx(1.0 - grid.max_confidence)
    assert u[at(grid, [0.85, 0.5, 0.5])] == 1.0


def test_unknown_space_far_from_every_surface_holds_a_share_of_the_unobserved_uncertainty():
    """`unobserved_reach` / `unobserved_far_weight`: behind the wall, the unknown voxels within
    reach of it hold all of `unobserved_uncertainty`, those beyond it the far share; before any
    surface is mapped every unknown voxel is far. Free and occupied voxels are unaffected."""
    depth, T = wall_frame()
    grid = make_grid(gamma=0.01, unobserved_reach=0.1, unobserved_far_weight=0.25)
    assert np.all(grid.geometric() == np.float32(0.25))  # nothing mapped yet: all far
    grid.integrate_depth(depth, np.full_like(depth, 0.75), K, T, max_range=5.0, stride=1)
    geo, occ = grid.geometric(), grid.occupancy()
    plain = make_grid(gamma=0.01)
    plain.integrate_depth(depth, np.full_like(depth, 0.75), K, T, max_range=5.0, stride=1)
    assert np.array_equal(occ, plain.occupancy())
    for x, expected in ((0.675, 1.0), (0.725, 1.0), (0.775, 0.25), (0.925, 0.25)):
        assert occ[at(grid, [x, 0.5, 0.5])] == -1
        assert geo[at(grid, [x, 0.5, 0.5])] == pytest.approx(expected), x
    known = occ != -1
    assert np.array_equal(geo[known], plain.geometric()[known])
    # the fused field follows: a far voxel is worth a quarter of a near one (plus gamma)
    u = grid.fused()
    near, far = u[at(grid, [0.675, 0.5, 0.5])], u[at(grid, [0.925, 0.5, 0.5])]
    assert far - 0.01 == pytest.approx(0.25 * (near - 0.01))
    with pytest.raises(InputError, match="unobserved_far_weight"):
        make_grid(gamma=0.01, unobserved_far_weight=1.5)
    with pytest.raises(InputError, match="unobserved_reach"):
        make_grid(gamma=0.01, unobserved_reach=-0.1)


def test_a_lone_uncertain_hit_makes_no_unknown_space_near_a_surface_until_seen_again():
    """`unobserved_reach_confidence`: the wall seen once at confidence 0.5 (stereo's wrong match
    on a periodic texture looks like this, and lands elsewhere from the next view) leaves the
    unknown space behind it far; seen at 0.85 it is near at once, and a second frame's hit at
    0.5 makes it near too. Occupancy and the surface's own uncertainty are unchanged."""
    depth, T = wall_frame()
    behind = [0.675, 0.5, 0.5]  # unknown, within reach of the wall

    def grid_after(*confidences, reach_confidence=0.8):
        grid = make_grid(
            gamma=0.01, unobserved_reach=0.1, unobserved_far_weight=0.25,
            unobserved_reach_confidence=reach_confidence,
        )  # fmt: skip
        for c in confidences:
            grid.integrate_depth(depth, np.full_like(depth, c), K, T, max_range=5.0, stride=1)
        return grid

    once = grid_after(0.5)
    assert once.occupancy()[at(once, behind)] == -1
    assert once.geometric()[at(once, behind)] == pytest.approx(0.25)
    assert grid_after(0.5, reach_confidence=0.0).geometric()[at(once, behind)] == 1.0
    assert grid_after(0.85).geometric()[at(once, behind)] == 1.0
    twice = grid_after(0.5, 0.5)
    assert twice.geometric()[at(twice, behind)] == 1.0
    plain = grid_after(0.5, reach_confidence=0.0)
    surface = once.occupancy() == 1
    assert np.array_equal(once.occupancy(), plain.occupancy()) and surface.any()
    assert np.array_equal(once.geometric()[surface], plain.geometric()[surface])
    with pytest.raises(InputError, match="unobserved_reach_confidence"):
        make_grid(gamma=0.01, unobserved_reach_confidence=1.5)


def test_unknown_space_far_from_surfaces_weighs_less_at_object_level_only():
    """The level defaults: an object's region box holds air around the objects (the top of a box
    drawn around one tall lamp); a room is explored, all of its unknown space counts."""
    from area3d_planner.config import PlannerConfig

    lo, hi = (-0.5, -0.5, 0.0), (0.5, 0.5, 1.0)
    grids = {
        level: PlannerConfig(level=level, roi_min=lo, roi_max=hi).fused_grid()
        for level in ("object", "room")
    }
    assert grids["object"].unobserved_far_weight == 0.25
    assert grids["room"].unobserved_far_weight == 1.0
    assert (
        PlannerConfig(level="room", unobserved_far_weight=0.5).fused_grid().unobserved_far_weight
        == 0.5
    )


def test_each_observation_lowers_geometric_uncertainty_under_the_product_rule():
    product, mean = make_grid(gamma=0.0), make_grid(gamma=0.0, geometric_rule="mean")
    depth, T = wall_frame()
    v = at(product, [0.62, 0.5, 0.5])
    seen = []
    for _ in range(4):
        for grid in (product, mean):
            grid.integrate_depth(depth, np.full_like(depth, 0.5), K, T, stride=1)
        seen.append((product.geometric()[v], mean.geometric()[v]))
    g_product = [p for p, _ in seen]
    np.testing.assert_allclose(g_product, 0.5 ** np.arange(1, 5), rtol=1e-5)
    assert all(m == pytest.approx(0.5) for _, m in seen)  # the mean rule never falls
    with pytest.raises(InputError, match="geometric_rule"):
        make_grid(gamma=0.0, geometric_rule="median")


def test_semantic_is_the_mean_of_the_splatted_maps_and_weighted_into_the_field():
    grid = make_grid(gamma=0.0, semantic_weight=0.5)
    depth, T = wall_frame()
    grid.integrate_depth(depth, np.ones_like(depth), K, T, stride=1)
    grid.integrate_semantic(np.full_like(depth, 0.2), depth, K, T)
    grid.integrate_semantic(np.full_like(depth, 0.6), depth, K, T)
    v = at(grid, [0.62, 0.5, 0.5])
    assert grid.semantic()[v] == pytest.approx(0.4)
    g = grid.geometric()[v]
    # the semantic term falls with the observations at half G's rate on a log scale
    assert grid.fused()[v] == pytest.approx(g + 0.5 * 0.4 * np.sqrt(g))
    assert grid.semantic()[at(grid, [0.35, 0.5, 0.5])] == 0.0


def test_bad_frames_are_rejected_naming_the_field():
    grid = make_grid(gamma=0.01)
    depth, T = wall_frame()
    with pytest.raises(InputError, match="confidence"):
        grid.integrate_depth(depth, np.ones((4, 4), np.float32), K, T)
    bad = T.copy()
    bad[:3, :3] *= 2
    with pytest.raises(InputError, match="T_world_cam"):
        grid.integrate_depth(depth, np.ones_like(depth), K, bad)


def test_cloud_holds_occupied_and_uncertain_voxels_with_their_fields():
    grid = make_grid(gamma=0.01)
    depth, T = wall_frame()
    grid.integrate_depth(depth, np.full_like(depth, 0.75), K, T, stride=1)
    cloud = grid_to_cloud(grid)
    assert cloud.dtype == CLOUD_DTYPE
    occ, u = grid.occupancy(), grid.fused()
    expected = np.flatnonzero((occ == 1) | (u > 0.01 + 1e-6))
    assert cloud.size == expected.size
    v = at(grid, [0.62, 0.5, 0.5])
    row = np.flatnonzero(
        np.all(
            np.abs(np.stack([cloud["x"], cloud["y"], cloud["z"]], 1) - grid.spec.centers()[v])
            < 1e-5,
            axis=1,
        )
    )
    assert row.size == 1
    r = cloud[row[0]]
    assert r["occupancy"] == 1 and r["geometric"] == pytest.approx(0.25)
    # one view with confidence 0.75: G 0.25, of which a new direction can remove 0.8125, + gamma
    assert r["uncertainty"] == pytest.approx(0.25 * 0.8125 + 0.01)
    assert r["hard"] == 0.0
    assert not np.any(cloud["occupancy"] == 0)  # known free voxels carry nothing


def _observation_by_arrays(grid, depth, conf, K, T, max_range, stride):
    """What a frame tells the grid, computed the direct way: every pixel back-projected into
    arrays, a bincount over the voxels, the carving into a fresh grid along every pixel but
    those whose finite depth has no confidence."""
    from area3d_msgs_py.backproject import backproject
    from area3d_msgs_py.carving import carve_depth_frame

    n = grid.spec.num_voxels
    points, pixel = backproject(depth, K, T)
    c = conf.reshape(-1)[pixel].astype(np.float64)
    vox, inside = grid.spec.flat_index(points)
    keep = inside & np.isfinite(c)
    vox, c = vox[keep], np.clip(c[keep], 0.0, 1.0)
    count = np.bincount(vox, minlength=n)
    hit = count > 0
    frame_conf = np.bincount(vox, weights=c, minlength=n)[hit] / count[hit]
    # a finite depth at confidence 0 or below (clipped to 0) is a guess: no free space along it
    carved = np.where(np.isfinite(depth) & (np.nan_to_num(conf, nan=1.0) <= 0), np.nan, depth)
    crossed = carve_depth_frame(
        grid.spec,
        carved,
        K,
        T,
        np.zeros(grid.spec.shape, np.uint8),
        stride,
        max_range,
        carve_no_return=np.isposinf(depth),
        count=False,
    ).reshape(-1)
    return np.flatnonzero(hit), frame_conf, np.flatnonzero((crossed > 0) & ~hit)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_frame_tallied_in_one_pass_tells_the_grid_what_the_direct_computation_does(seed):
    # random poses (some looking out of the grid), depths with holes and beyond the grid,
    # confidences with NaN and outside [0, 1]; frames one after another on one grid, so a scratch
    # not cleared after a frame would show in the next
    rng = np.random.default_rng(seed)
    grid = make_grid(gamma=0.01)
    for _ in range(6):
        eye = rng.uniform(0.05, 0.95, 3)
        T = look_at(eye, eye + rng.normal(size=3))
        depth = rng.uniform(0.02, 1.5, (48, 64)).astype(np.float32)
        depth[rng.random(depth.shape) < 0.1] = np.nan
        depth[20:30, 10:40] = np.inf  # no return within range: carves to max range
        depth[rng.random(depth.shape) < 0.05] = np.inf
        conf = rng.uniform(-0.2, 1.2, depth.shape).astype(np.float32)
        conf[rng.random(conf.shape) < 0.1] = np.nan
        for stride in (1, 2, 3):
            got = grid.observe_depth(depth, conf, K, T, 1.0, stride)
            hit, frame_conf, free = _observation_by_arrays(grid, depth, conf, K, T, 1.0, stride)
            assert hit.size > 0 and free.size > 0
            np.testing.assert_array_equal(got.hit, hit)
            np.testing.assert_array_equal(got.confidence, frame_conf.astype(np.float32))
            np.testing.assert_array_equal(got.free, free)
            grid.apply_depth(got)


def test_a_frame_that_fails_part_way_leaves_nothing_in_the_next_frames_tally(monkeypatch):
    import area3d_planner.observation as observation

    grid = make_grid(gamma=0.01)
    depth, T = wall_frame()
    conf = np.full_like(depth, 0.75)
    real_carve = observation.carve_depth_frame

    def failing_carve(*args, **kwargs):
        real_carve(*args, **kwargs)  # the scratch has the frame's hits and crossings by now
        raise RuntimeError("carving failed")

    monkeypatch.setattr(observation, "carve_depth_frame", failing_carve)
    with pytest.raises(RuntimeError):
        grid.observe_depth(depth, conf, K, T, 5.0, 1)
    monkeypatch.setattr(observation, "carve_depth_frame", real_carve)
    got = grid.observe_depth(depth, conf, K, T, 5.0, 1)
    hit, frame_conf, free = _observation_by_arrays(grid, depth, conf, K, T, 5.0, 1)
    np.testing.assert_array_equal(got.hit, hit)
    np.testing.assert_array_equal(got.confidence, frame_conf.astype(np.float32))
    np.testing.assert_array_equal(got.free, free)


def test_occupancy_is_the_sign_of_the_clamped_log_odds_of_observed_voxels():
    """The compiled pass against its definition, on counts where hits and misses nearly cancel
    (7 hits x 0.847 against 15 misses x -0.405) and on counts of whole frames and fractions."""
    grid = make_grid(gamma=0.01)
    rng = np.random.default_rng(4)
    n = grid.spec.num_voxels
    grid.hit_count[:] = rng.integers(0, 20, n) * rng.choice([1.0, 0.5, 0.0], n)
    grid.free_count[:] = rng.integers(0, 40, n) * rng.choice([1.0, 0.25, 0.0], n)
    lo = grid.log_odds()
    observed = (grid.hit_count + grid.free_count) > 0
    expect = np.where(observed, np.where(lo > 0, 1, 0), -1)
    occ = grid.occupancy()
    assert occ.dtype == np.int8 and np.array_equal(occ, expect)
    assert {-1, 0, 1} <= set(np.unique(occ).tolist())
    near = np.abs(grid.hit_count * 0.847 + grid.free_count * -0.405) < 0.1
    assert np.any(near & observed)  # the near-cancelling counts are among them


def _fused_by_whole_arrays(grid):
    """`FusedGrid.fused` as numpy passes over whole arrays (its definition, and the code before
    the one-pass kernel): the oracle of the test below."""
    occ = grid.occupancy()
    g = grid.geometric(occ)
    s = np.zeros(grid.spec.num_voxels, np.float32)
    seen = grid.sem_count > 0
    s[seen] = grid.sem_sum[seen] / grid.sem_count[seen]
    if grid.geometric_rule == "product":
        s = s * np.sqrt(g)
    u = np.maximum(g + np.float32(grid.semantic_weight) * s, 0.0)
    if grid.gain_rule == "removable":
        n = np.bitwise_count(grid.directions).astype(np.uint8).astype(np.float32)
        c = grid.best_confidence
        u = u * (c + (1.0 - c) * np.float32(grid.retry_gain) ** n).astype(np.float32)
    u = u + np.float32(grid.gamma)
    u[occ == 0] = 0.0
    u[~grid.roi_mask] = 0.0
    return u.astype(np.float32)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    geometric_rule=st.sampled_from(["product", "mean"]),
    gain_rule=st.sampled_from(["removable", "held"]),
    semantic_weight=st.sampled_from([0.0, 0.3, 1.0, 2.5]),
    gamma=st.sampled_from([0.0, 0.01, 0.2]),
    retry_gain=st.sampled_from([0.0, 0.3, 0.5, 1.0]),
)
def test_the_fused_field_and_achievability_equal_their_whole_array_definitions_bit_for_bit(
    seed, geometric_rule, gain_rule, semantic_weight, gamma, retry_gain
):
    """The one-pass field (and the achievability's looked-up powers) against numpy's passes over
    whole arrays, on random tallies: hits with any confidence, voxels seen from none to all 32
    directions, semantic means where frames landed and none elsewhere, every rule."""
    grid = make_grid(
        gamma=gamma, semantic_weight=semantic_weight, geometric_rule=geometric_rule,
        gain_rule=gain_rule, retry_gain=retry_gain, unobserved_uncertainty=0.8,
    )  # fmt: skip
    rng = np.random.default_rng(seed)
    n = grid.spec.num_voxels
    hits = rng.integers(0, 6, n) * rng.choice([1.0, 0.0], n)
    grid.hit_count[:] = hits
    grid.free_count[:] = rng.integers(0, 9, n) * rng.choice([1.0, 0.0], n)
    conf = rng.random(n).astype(np.float32)
    grid.conf_sum[:] = hits * conf
    grid.log_residual[:] = hits * np.log1p(-0.999 * conf)
    grid.best_confidence[:] = np.where(hits > 0, conf, 0.0)
    counts = rng.integers(0, 4, n) * rng.choice([1.0, 0.0], n)
    grid.sem_count[:] = counts
    grid.sem_sum[:] = counts * rng.random(n)
    bits = rng.integers(0, 33, n)
    grid.directions[:] = np.where(bits == 32, 2**32 - 1, (1 << bits.astype(np.uint64)) - 1)
    got = grid.fused()
    want = _fused_by_whole_arrays(grid)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
    c = grid.best_confidence
    powers = np.float32(retry_gain) ** np.bitwise_count(grid.directions).astype(np.float32)
    want_a = (c + (1.0 - c) * powers).astype(np.float32)
    np.testing.assert_array_equal(grid.achievability().view(np.uint32), want_a.view(np.uint32))
    occ = grid.occupancy()
    assert {-1, 0, 1} <= set(np.unique(occ[grid.roi_mask]).tolist())  # every kind of voxel


@pytest.mark.parametrize("confidence, undone", [(0.04, True), (0.9, False)])
def test_a_match_in_empty_air_is_undone_by_the_next_ray_when_occupancy_weighs_confidence(
    confidence, undone
):
    """A frame matches a false surface at x = 0.625 (stereo in the sky); the next frame, from the
    same place, sees the true wall at 0.875 through it: its ray crosses the false voxel once. By
    hits (OctoMap) one miss never undoes a hit; weighted by confidence a hit at 0.04 is undone,
    one at 0.9 stands (it takes three misses), and the wall is occupied either way."""
    false_wall, true_wall = wall_frame()[0], np.full((48, 64), 0.775, np.float32)
    T = wall_frame()[1]
    grids = {}
    for rule in ("hits", "confidence"):
        grid = make_grid(gamma=0.01, occupancy_rule=rule)
        grid.integrate_depth(false_wall, np.full_like(false_wall, confidence), K, T, stride=1)
        grid.integrate_depth(true_wall, np.full_like(true_wall, 0.9), K, T, stride=1)
        grids[rule] = grid.occupancy()
    air = at(make_grid(gamma=0.01), [0.62, 0.5, 0.5])
    wall = at(make_grid(gamma=0.01), [0.87, 0.5, 0.5])
    assert grids["hits"][air] == 1
    assert grids["confidence"][air] == (0 if undone else 1)
    assert grids["hits"][wall] == grids["confidence"][wall] == 1
    with pytest.raises(InputError, match="^occupancy_rule: "):
        make_grid(gamma=0.01, occupancy_rule="votes")
