"""Hard voxels grouped into regions: 26-connected groups with their centroid, bounding box, voxel
count, directions and mean uncertainty, largest first; from synthetic voxel sets and from a fused
grid whose two surface bands no direction resolves."""

from __future__ import annotations

import numpy as np
import pytest

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec
from area3d_msgs_py.hard_region import HARD_REGION_DTYPE
from area3d_planner.cloud import grid_to_cloud
from area3d_planner.fusion import FusedGrid
from area3d_planner.hard_regions import (
    cloud_hard_regions,
    grid_voxel_size,
    hard_regions,
    points_hard_regions,
)
from area3d_planner.test.conftest import WALL_DIRECTIONS, WALL_K, banded_wall_view

LOWER = np.array([-1.0, 0.0, 2.0])
VOXEL = 0.1


def test_two_separate_clusters_are_two_regions_with_their_centroids_extents_and_counts():
    block = [(i, j, 0) for i in (2, 3) for j in (5, 6, 7)]  # 2 x 3 x 1 voxels
    line = [(10, 1, 4), (10, 1, 5)]  # 1 x 1 x 2, far from the block
    ijk = np.array(block + line)
    directions = np.array([3, 4, 3, 3, 5, 3, 6, 3])
    uncertainty = np.array([0.2] * 6 + [0.5, 0.7])
    regions = hard_regions(ijk, LOWER, VOXEL, directions, uncertainty)
    assert regions.dtype == HARD_REGION_DTYPE and len(regions) == 2
    big, small = regions
    assert big["voxel_count"] == 6 and small["voxel_count"] == 2
    # centroid: the mean of the voxel centres lower + (ijk + 0.5) voxel
    np.testing.assert_allclose(big["centroid"], LOWER + (np.array([2.5, 6.0, 0.0]) + 0.5) * VOXEL)
    np.testing.assert_allclose(small["centroid"], LOWER + (np.array([10, 1, 4.5]) + 0.5) * VOXEL)
    # extent: the voxels' bounding box, voxel edges included
    np.testing.assert_allclose(big["extent"], [0.2, 0.3, 0.1])
    np.testing.assert_allclose(small["extent"], [0.1, 0.1, 0.2])
    assert big["direction_count"] == 5 and small["direction_count"] == 6  # the most of any voxel
    assert big["mean_uncertainty"] == pytest.approx(0.2)
    assert small["mean_uncertainty"] == pytest.approx(0.6)


def test_voxels_touching_at_an_edge_or_a_corner_are_one_region_and_a_lone_voxel_is_kept():
    corner = [(0, 0, 0), (1, 1, 1), (2, 2, 1)]  # corner, then edge neighbours
    lone = [(5, 5, 5)]
    ijk = np.array(corner + lone)
    regions = hard_regions(ijk, np.zeros(3), 1.0, np.full(4, 3), np.ones(4))
    assert list(regions["voxel_count"]) == [3, 1]
    np.testing.assert_allclose(regions[0]["extent"], [3.0, 3.0, 2.0])
    np.testing.assert_allclose(regions[1]["extent"], [1.0, 1.0, 1.0])
    np.testing.assert_allclose(regions[1]["centroid"], [5.5, 5.5, 5.5])


def test_regions_of_equal_size_come_most_uncertain_first_and_none_give_an_empty_array():
    ijk = np.array([(0, 0, 0), (9, 9, 9)])
    regions = hard_regions(ijk, np.zeros(3), 1.0, np.array([3, 3]), np.array([0.1, 0.9]))
    assert list(regions["mean_uncertainty"]) == pytest.approx([0.9, 0.1])
    empty = hard_regions(np.zeros((0, 3), int), np.zeros(3), 1.0, [], [])
    assert empty.dtype == HARD_REGION_DTYPE and len(empty) == 0


def test_bad_inputs_name_the_field():
    with pytest.raises(InputError, match="ijk"):
        hard_regions(np.zeros((2, 3)), np.zeros(3), 1.0, [3, 3], [1, 1])
    with pytest.raises(InputError, match="direction_count"):
        hard_regions(np.zeros((2, 3), int), np.zeros(3), 1.0, [3], [1, 1])
    with pytest.raises(InputError, match="voxel_size"):
        hard_regions(np.zeros((1, 3), int), np.zeros(3), 0.0, [3], [1])


def test_a_fused_wall_with_two_bands_no_direction_resolves_has_two_hard_regions():
    spec = GridSpec.from_bounds(np.zeros(3), np.ones(3), 0.05)
    grid = FusedGrid(spec, np.zeros(3), np.ones(3), gamma=0.0)
    for azimuth, elevation in WALL_DIRECTIONS:
        depth, confidence, T = banded_wall_view(azimuth, elevation)
        grid.integrate_depth(depth, confidence, WALL_K, T, stride=1)
    cloud = grid_to_cloud(grid)
    regions = cloud_hard_regions(cloud, grid)
    # each band: 3 voxels (y) x 8 voxels (z) of the wall's voxel layer (x in [0.6, 0.65])
    assert list(regions["voxel_count"]) == [24, 24]
    assert int(regions["voxel_count"].sum()) == int(grid.hard().sum())
    by_y = regions[np.argsort(regions["centroid"][:, 1])]
    np.testing.assert_allclose(by_y["centroid"], [[0.625, 0.225, 0.5], [0.625, 0.775, 0.5]])
    np.testing.assert_allclose(by_y["extent"], [[0.05, 0.15, 0.4]] * 2)
    assert np.all(regions["direction_count"] >= 3)
    hard = grid.hard()
    u, centres = grid.fused()[hard], spec.centers()[hard]
    for region in regions:
        mine = np.abs(centres[:, 1] - region["centroid"][1]) < 0.2  # the band's hard voxels
        assert region["mean_uncertainty"] == pytest.approx(u[mine].mean(), rel=1e-5)
        directions = grid.direction_count()[hard][mine]
        assert region["direction_count"] == directions.max()
    # the same regions from the saved grid's points (the report's path), voxel size inferred
    assert grid_voxel_size(np.stack([cloud[a] for a in "xyz"], 1)) == pytest.approx(0.05)
    rows = cloud["hard"] > 0
    again = points_hard_regions(
        np.stack([cloud[a][rows] for a in "xyz"], 1), cloud["uncertainty"][rows], 0.05
    )
    np.testing.assert_array_equal(again["voxel_count"], regions["voxel_count"])
    np.testing.assert_allclose(again["centroid"], regions["centroid"], atol=1e-6)
