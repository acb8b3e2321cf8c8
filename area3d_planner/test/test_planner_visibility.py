import dataclasses

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from area3d_perception.grid import GridSpec
from area3d_planner.fusion import FusedGrid
from area3d_planner.greedy import GreedyParams, lazy_greedy
from area3d_planner.visibility import (
    VisibilityCache,
    VisibilityParams,
    candidate_seeds,
    look_rotation,
    orientation_bins,
)

FAST = VisibilityParams(yaw_bins=8, pitch_bins=3, pitch_min_deg=-30, pitch_max_deg=30, mc_rays=128)


def test_orientation_bins_are_optical_frames_with_zero_roll():
    forward, rotations = orientation_bins(VisibilityParams())
    assert forward.shape == (60, 3) and rotations.shape == (60, 3, 3)
    for f, R in zip(forward, rotations, strict=True):
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
        np.testing.assert_allclose(R[:, 2], f, atol=1e-12)  # optical z along the bin direction
        assert abs(R[2, 0]) < 1e-12  # image x axis horizontal
        assert R[2, 1] <= 1e-12  # image y axis points down (or horizontal)
    R = look_rotation(np.array([0.0, 0.0, -1.0]))  # straight down still a rotation
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_seeds_stay_in_the_workspace_and_clear_of_geometry():
    rng = np.random.default_rng(3)
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    occ = np.where(rng.random(spec.num_voxels) < 0.03, 1, 0).astype(np.int8)
    lo, hi = np.array([0.1, 0.0, 0.2]), np.array([0.9, 1.0, 0.8])
    seeds = candidate_seeds(lo, hi, 0.1, spec, occ, clearance=0.05)
    assert seeds.shape[0] > 0
    assert np.all((seeds >= lo) & (seeds <= hi))
    d = cdist(seeds, spec.centers()[occ == 1]).min(axis=1)
    assert np.all(d > 0.05 + 0.025)
    # and nothing valid was dropped: every lattice point clear of geometry is a seed
    all_pts = candidate_seeds(lo, hi, 0.1, spec, np.zeros_like(occ), clearance=0.05)
    clear = cdist(all_pts, spec.centers()[occ == 1]).min(axis=1) > 0.075
    assert clear.sum() == seeds.shape[0]


def test_seeds_in_unknown_space_need_permission():
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    occ = np.full(spec.num_voxels, -1, np.int8)
    assert candidate_seeds(np.zeros(3), np.ones(3), 0.25, spec, occ).shape[0] == 0
    assert (
        candidate_seeds(np.zeros(3), np.ones(3), 0.25, spec, occ, allow_unknown=True).shape[0] == 64
    )


def test_voxels_behind_an_occupied_wall_are_never_in_a_mask():
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    occ = np.full(spec.shape, -1, np.int8)
    occ[:10] = 0  # free half x < 0.5 where the cameras are
    occ[10] = 1  # a full wall x in [0.5, 0.55)
    seeds = candidate_seeds(np.zeros(3), np.array([0.45, 1.0, 1.0]), 0.15, spec, occ.ravel())
    cache = VisibilityCache.build(spec, occ.ravel(), seeds, FAST)
    ix = np.unravel_index(cache.voxel_ids, spec.shape)[0]
    assert cache.voxel_ids.size > 0
    assert ix.max() == 10  # the wall is seen, nothing behind it
    assert np.all(cache.weights > 0)
    fraction = VisibilityCache.build(
        spec, occ.ravel(), seeds, dataclasses.replace(FAST, weighting="ray_fraction")
    )
    assert np.all(fraction.weights > 0) and np.all(fraction.weights <= 1)


@pytest.mark.parametrize("distance", [0.3, 0.6])
def test_coverage_weights_count_the_voxels_a_view_sees_at_any_distance(distance):
    # A wall filling the whole frustum: the weights of one view must add up to the number of wall
    # voxels inside the frustum, each foreshortened by the cosine of its viewing angle (what a
    # camera's pixels actually cover), near or far.
    size = 0.01
    spec = GridSpec.from_bounds(np.array([0.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0]), size)
    occ = np.zeros(spec.shape, np.int8)
    wall_i = int(round(distance / size))
    occ[wall_i] = 1
    params = VisibilityParams(
        yaw_bins=4, pitch_bins=1, pitch_min_deg=0, pitch_max_deg=0, mc_rays=4096
    )
    cache = VisibilityCache.build(spec, occ.ravel(), np.array([[0.0, 0.0, 0.0]]), params)
    view = int(np.argmax(cache.forward[:, 0]))  # the bin looking along +x
    ids, weights = cache.mask(view)
    assert np.all(np.unravel_index(ids, spec.shape)[0] == wall_i)
    depth = wall_i * size  # the wall's front face
    c = (np.arange(-1.0, 1.0, size) + size / 2)[:, None]
    y, z = np.broadcast_arrays(c, c.T)
    in_view = (np.abs(y) <= depth) & (np.abs(z) <= depth * 480 / 640)  # 90 degree hfov, 4:3
    expected = np.sum(depth / np.sqrt(depth**2 + y**2 + z**2)[in_view])
    assert abs(weights.sum() - expected) < 0.05 * expected


def test_masks_do_not_depend_on_the_thread_count():
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    rng = np.random.default_rng(1)
    occ = rng.choice(np.array([-1, 0, 1], np.int8), size=spec.num_voxels, p=[0.3, 0.65, 0.05])
    seeds = rng.random((7, 3))
    a = VisibilityCache.build(spec, occ, seeds, FAST, threads=1)
    b = VisibilityCache.build(spec, occ, seeds, FAST, threads=2)
    np.testing.assert_array_equal(a.indptr, b.indptr)
    np.testing.assert_array_equal(a.voxel_ids, b.voxel_ids)
    np.testing.assert_array_equal(a.weights, b.weights)


def test_first_view_looks_into_the_unobserved_pocket_through_its_opening(
    pocket_grid: FusedGrid, pocket_interior
):
    spec = pocket_grid.spec
    occ = pocket_grid.occupancy()
    seeds = candidate_seeds(np.full(3, 0.05), np.full(3, 0.95), 0.1, spec, occ, clearance=0.05)
    cache = VisibilityCache.build(spec, occ, seeds, VisibilityParams(mc_rays=256))
    sel = lazy_greedy(cache, pocket_grid.fused(), 1, GreedyParams())
    view = sel.views[0]
    ids, w = cache.mask(view)
    T = cache.view_pose(view)
    assert T[0, 3] > 0.65  # on the open side of the box
    assert T[0, 2] < -0.5  # looking towards -x, into the opening
    inside = pocket_interior[ids]
    assert inside.any() and w[inside].sum() > 0
    # no view from the closed sides sees the interior
    closed = cache.seeds[:, 0] < 0.3
    for s in np.flatnonzero(closed):
        for b in range(cache.num_bins):
            assert not pocket_interior[cache.mask(s * cache.num_bins + b)[0]].any()
