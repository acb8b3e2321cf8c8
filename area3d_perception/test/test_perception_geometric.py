"""Confidence splatting, free-space carving and the geometric uncertainty field."""

import numpy as np
import pytest

from area3d_msgs_py.carving import carve_depth_frame, carve_free_space, frame_rays
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec
from area3d_perception.geometric import (
    geometric_uncertainty,
    splat_confidence,
    splat_depth_frame,
)

SPEC = GridSpec(origin=(-0.3, 0.2, 1.0), voxel_size=0.1, shape=(10, 6, 5))


def voxel_centre(spec: GridSpec, ijk) -> np.ndarray:
    return spec.lower + (np.asarray(ijk, dtype=float) + 0.5) * spec.voxel_size


def test_splat_puts_each_point_in_its_voxel_and_conserves_weight():
    rng = np.random.default_rng(0)
    ijk = np.stack([rng.integers(0, n, 500) for n in SPEC.shape], axis=1)
    offsets = rng.uniform(-0.45, 0.45, (500, 3)) * SPEC.voxel_size
    points = voxel_centre(SPEC, ijk) + offsets
    weights = rng.uniform(0, 1, 500)
    evidence, hits = splat_confidence(SPEC, points, weights)
    assert evidence.sum() == pytest.approx(weights.sum(), rel=1e-5)
    assert hits.sum() == 500
    expected_e = np.zeros(SPEC.shape)
    expected_h = np.zeros(SPEC.shape)
    for (i, j, k), wgt in zip(ijk, weights, strict=True):
        expected_e[i, j, k] += wgt
        expected_h[i, j, k] += 1
    np.testing.assert_allclose(evidence, expected_e, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(hits, expected_h)


def test_splat_ignores_points_outside_the_grid_and_non_finite_ones():
    inside = voxel_centre(SPEC, (2, 3, 4))
    points = np.array([inside, SPEC.lower - 0.01, SPEC.upper + 0.01, [np.nan, 0.5, 1.2], inside])
    weights = np.array([0.5, 1.0, 1.0, 1.0, np.nan])
    evidence, hits = splat_confidence(SPEC, points, weights)
    assert hits.sum() == 1 and hits[2, 3, 4] == 1 and evidence[2, 3, 4] == pytest.approx(0.5)


def test_splat_accumulates_in_place_across_calls():
    evidence = np.zeros(SPEC.shape, np.float32)
    hits = np.zeros(SPEC.shape, np.float32)
    p = voxel_centre(SPEC, (1, 1, 1))[None]
    out = splat_confidence(SPEC, p, [0.25], evidence, hits)
    splat_confidence(SPEC, p, [0.75], evidence, hits)
    assert out[0] is evidence and evidence[1, 1, 1] == pytest.approx(1.0) and hits[1, 1, 1] == 2


def test_carving_an_axis_aligned_ray_marks_exactly_the_voxels_before_the_hit():
    free = np.zeros(SPEC.shape, np.int32)
    origin = voxel_centre(SPEC, (0, 2, 3))
    hit = voxel_centre(SPEC, (7, 2, 3)) + [0.02, 0.0, 0.0]
    carve_free_space(SPEC, origin, hit[None], free)
    expected = np.zeros(SPEC.shape, np.int32)
    expected[0:7, 2, 3] = 1
    np.testing.assert_array_equal(free, expected)
    # The same along -y, with the origin at a voxel face.
    free[:] = 0
    origin = voxel_centre(SPEC, (4, 5, 1)) + [0.0, 0.05, 0.0]
    carve_free_space(SPEC, origin, voxel_centre(SPEC, (4, 1, 1))[None], free)
    expected[:] = 0
    expected[4, 2:6, 1] = 1
    np.testing.assert_array_equal(free, expected)


def segment_voxels(spec: GridSpec, a: np.ndarray, b: np.ndarray, samples: int = 200_000) -> set:
    t = np.linspace(0.0, 1.0, samples)[:, None]
    ijk, inside = spec.voxel_index(a + t * (b - a))
    return {tuple(v) for v in ijk[inside]}


def test_carving_oblique_rays_matches_dense_sampling_and_never_marks_the_hit_voxel():
    rng = np.random.default_rng(5)
    for _ in range(30):
        # Origins both inside and outside the grid; ends inside it.
        origin = rng.uniform(SPEC.lower - 0.3, SPEC.upper + 0.3)
        end = rng.uniform(SPEC.lower + 1e-3, SPEC.upper - 1e-3)
        free = np.zeros(SPEC.shape, np.uint16)
        carve_free_space(SPEC, origin, end[None], free)
        end_voxel = tuple(SPEC.voxel_index(end[None])[0][0])
        expected = segment_voxels(SPEC, origin, end) - {end_voxel}
        assert {tuple(v) for v in np.argwhere(free)} == expected
        assert free[end_voxel] == 0
        assert free.max() <= 1


def test_rays_without_a_return_carve_to_their_end_without_marking_it():
    free = np.zeros(SPEC.shape, np.int32)
    origin = voxel_centre(SPEC, (0, 0, 0))
    end = voxel_centre(SPEC, (5, 0, 0))
    carve_free_space(SPEC, origin, end[None], free, hit_mask=np.array([False]), surface_margin=0.25)
    assert free[0:5, 0, 0].tolist() == [1] * 5 and free[5:, 0, 0].sum() == 0


def test_surface_margin_keeps_hit_rays_away_from_the_surface():
    free = np.zeros(SPEC.shape, np.int32)
    origin = voxel_centre(SPEC, (0, 0, 0))
    end = voxel_centre(SPEC, (9, 0, 0))
    carve_free_space(SPEC, origin, end[None], free, surface_margin=0.27)
    # The hit is 0.9 m away; carving stops 0.27 m short, 0.68 m past the grid face (the origin
    # sits 0.05 m inside voxel 0), so only voxels 0..5 (ending at <= 0.6 m) are carved.
    assert free[:, 0, 0].tolist() == [1, 1, 1, 1, 1, 1, 0, 0, 0, 0]


def test_carving_counts_every_ray_through_a_voxel():
    free = np.zeros(SPEC.shape, np.int32)
    origin = voxel_centre(SPEC, (0, 2, 2))
    ends = np.stack([voxel_centre(SPEC, (9, 2, 2))] * 3)
    carve_free_space(SPEC, origin, ends, free)
    assert free[0:9, 2, 2].tolist() == [3] * 9


def look_at_plus_y(position) -> np.ndarray:
    """Optical frame (z forward, x right, y down) looking along world +y, z up."""
    T = np.eye(4)
    T[:3, :3] = np.column_stack([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    T[:3, 3] = position
    return T


def test_a_depth_frame_carves_the_space_before_a_wall_and_splats_the_wall():
    spec = GridSpec.from_bounds(np.array([-1.0, 0.0, -1.0]), np.array([1.0, 3.0, 1.0]), 0.1)
    h, w = 60, 80
    K = np.array([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1.0]])
    T = look_at_plus_y([0.0, 0.05, 0.0])
    depth = np.full((h, w), 2.0, np.float32)  # a wall at y = 2.05
    free = np.zeros(spec.shape, np.int32)
    carve_depth_frame(spec, depth, K, T, free, stride=1)
    evidence = np.zeros(spec.shape, np.float32)
    hits = np.zeros(spec.shape, np.float32)
    splat_depth_frame(spec, depth, np.full((h, w), 0.8, np.float32), K, T, evidence, hits)
    ix = spec.voxel_index(np.array([[0.0, 0.0, 0.0]]))[0][0, 0]
    iz = ix
    column = free[ix, :, iz]
    assert np.all(column[:20] > 0)  # y in [0, 2.0): in front of the wall
    assert np.all(column[20:] == 0)  # the wall voxel and behind it
    assert hits[ix, 20, iz] > 0 and hits[:, :20].sum() == 0 and hits[:, 21:].sum() == 0
    u = geometric_uncertainty(evidence, hits, free > 0)
    assert u[ix, 20, iz] == pytest.approx(0.2, abs=1e-6)
    assert u[ix, 10, iz] == 0.0 and u[ix, 25, iz] == 1.0


def test_pixels_without_return_carve_up_to_max_range():
    spec = GridSpec.from_bounds(np.array([-0.5, 0.0, -0.5]), np.array([0.5, 6.0, 0.5]), 0.1)
    h, w = 8, 8
    K = np.array([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1.0]])
    T = look_at_plus_y([0.0, 0.0, 0.0])
    depth = np.full((h, w), np.nan, np.float32)
    free = np.zeros(spec.shape, np.int32)
    carve_depth_frame(spec, depth, K, T, free, stride=1, max_range=3.0)
    reached = np.argwhere(free)[:, 1].max() * 0.1 + 0.1
    assert 2.5 < reached <= 3.0
    free[:] = 0
    carve_depth_frame(spec, depth, K, T, free, stride=1, max_range=3.0, carve_no_return=False)
    assert free.sum() == 0


def test_uncertainty_is_high_unobserved_low_for_confident_hits_and_zero_when_free():
    shape = (3, 1, 1)
    conf_sum = np.array([0.0, 0.0, 2.7], np.float32).reshape(shape)
    hits = np.array([0.0, 0.0, 3.0], np.float32).reshape(shape)
    observed = np.array([False, True, True]).reshape(shape)
    u = geometric_uncertainty(conf_sum, hits, observed)
    assert u.ravel().tolist() == pytest.approx([1.0, 0.0, 0.1])
    assert geometric_uncertainty(conf_sum, hits, observed, unobserved_uncertainty=0.4)[
        0, 0, 0
    ] == pytest.approx(0.4)
    # Less confident evidence means more uncertainty.
    low = geometric_uncertainty(conf_sum * 0.5, hits, observed)
    assert low[2, 0, 0] > u[2, 0, 0]


def test_bad_input_is_rejected_naming_the_field():
    with pytest.raises(InputError, match="^points: "):
        splat_confidence(SPEC, np.zeros((4, 2)), np.zeros(4))
    with pytest.raises(InputError, match="^weights: "):
        splat_confidence(SPEC, np.zeros((4, 3)), np.zeros(3))
    with pytest.raises(InputError, match="^evidence: "):
        splat_confidence(
            SPEC, np.zeros((4, 3)), np.zeros(4), evidence=np.zeros((2, 2, 2), np.float32)
        )
    with pytest.raises(InputError, match="^free_count: "):
        carve_free_space(SPEC, np.zeros(3), np.zeros((1, 3)), np.zeros((3, 3, 3), np.int32))
    with pytest.raises(InputError, match="^free_count: "):
        carve_free_space(
            SPEC, np.zeros(3), np.zeros((1, 3)), np.zeros(SPEC.shape[::-1], np.int32).T
        )
    with pytest.raises(InputError, match="^origin: "):
        carve_free_space(
            SPEC, np.array([np.nan, 0, 0]), np.zeros((1, 3)), np.zeros(SPEC.shape, np.int32)
        )
    with pytest.raises(InputError, match="^hit_mask: "):
        carve_free_space(
            SPEC, np.zeros(3), np.zeros((2, 3)), np.zeros(SPEC.shape, np.int32), np.ones(3, bool)
        )
    with pytest.raises(InputError, match="^hit_count/observed_mask: "):
        geometric_uncertainty(np.zeros((2, 2, 2)), np.zeros((2, 2, 1)), np.zeros((2, 2, 2), bool))


def test_frame_helpers_reject_bad_images():
    K = np.eye(3)
    free = np.zeros(SPEC.shape, np.int32)
    with pytest.raises(InputError, match="^depth: "):
        carve_depth_frame(SPEC, np.zeros((4, 4, 2), np.float32), K, np.eye(4), free)
    with pytest.raises(InputError, match="^stride: "):
        carve_depth_frame(SPEC, np.zeros((4, 4), np.float32), K, np.eye(4), free, stride=0)
    e = np.zeros(SPEC.shape, np.float32)
    with pytest.raises(InputError, match="^confidence: "):
        splat_depth_frame(
            SPEC,
            np.zeros((4, 4), np.float32),
            np.zeros((4, 5), np.float32),
            K,
            np.eye(4),
            e,
            e.copy(),
        )


def _tilted_frame(h: int, w: int):
    """A depth frame of a slanted floor and a box, with holes (NaN, inf, 0 and beyond range),
    looking along +y from outside SPEC-like grid, and the grid it looks into."""
    rng = np.random.default_rng(11)
    spec = GridSpec.from_bounds(np.array([-1.0, 0.0, -1.0]), np.array([1.0, 3.0, 1.0]), 0.07)
    K = np.array([[w * 0.6, 0, w / 2 + 0.3], [0, w * 0.6, h / 2 - 0.2], [0, 0, 1.0]])
    T = look_at_plus_y([0.03, -0.4, 0.11])
    rows = np.linspace(0.5, 4.5, h, dtype=np.float32)[:, None]
    depth = np.broadcast_to(rows, (h, w)).copy()
    depth[h // 4 : h // 2, w // 3 : w // 2] = 1.2  # a box in front of the floor
    holes = rng.random((h, w))
    depth[holes < 0.05] = np.nan
    depth[(holes >= 0.05) & (holes < 0.07)] = np.inf
    depth[(holes >= 0.07) & (holes < 0.08)] = 0.0
    depth[: h // 6, : w // 5] = np.nan  # a region without returns
    return spec, depth, K, T


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_marking_a_frame_in_one_pass_equals_its_rays_walked_one_by_one(stride):
    """The fused pass (count=False, no surface margin) marks exactly the voxels that the frame's
    rays (`frame_rays`) mark through `carve_free_space`, for every rule of no-return pixels."""
    spec, depth, K, T = _tilted_frame(45, 61)
    region = np.zeros(depth.shape, bool)
    region[: depth.shape[0] // 3] = True
    for rule in (True, False, region):
        fused = carve_depth_frame(
            spec, depth, K, T, np.zeros(spec.shape, np.uint8), stride, 3.0, carve_no_return=rule,
            count=False,
        )  # fmt: skip
        points, hit = frame_rays(depth, K, T, stride, 3.0)
        keep = hit | (rule if isinstance(rule, bool) else region[::stride, ::stride].reshape(-1))
        walked = carve_free_space(
            spec, T[:3, 3], points[keep], np.zeros(spec.shape, np.uint8), hit[keep], count=False
        )
        assert walked.sum() > 100  # the frame carves a real volume
        np.testing.assert_array_equal(fused, walked)
    with pytest.raises(InputError, match="T_world_cam"):
        bad = T.copy()
        bad[0, 3] = np.nan
        carve_depth_frame(spec, depth, K, bad, np.zeros(spec.shape, np.uint8), count=False)
    with pytest.raises(InputError, match="free_count"):
        carve_depth_frame(spec, depth, K, T, np.zeros(spec.shape, np.int32), count=False)
    with pytest.raises(InputError, match="carve_no_return"):
        carve_depth_frame(
            spec, depth, K, T, np.zeros(spec.shape, np.uint8), carve_no_return=region[1:],
            count=False,
        )  # fmt: skip


def test_marking_in_parallel_finds_exactly_the_voxels_counting_finds():
    """count=False (parallel rays, uint8 marks) carves the set that counting finds > 0."""
    rng = np.random.default_rng(3)
    spec = GridSpec.from_bounds(np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5]), 0.05)
    origin = np.array([0.02, -0.9, 0.13])  # outside the grid: rays enter it
    ends = rng.uniform(-0.7, 0.7, size=(5000, 3))
    hit = rng.random(5000) < 0.7
    counted = carve_free_space(spec, origin, ends, np.zeros(spec.shape, np.int32), hit)
    marked = carve_free_space(spec, origin, ends, np.zeros(spec.shape, np.uint8), hit, count=False)
    assert counted.max() > 1  # rays overlap: counting and marking differ in value
    assert marked.max() == 1
    np.testing.assert_array_equal(marked > 0, counted > 0)
    with pytest.raises(InputError, match="free_count"):
        carve_free_space(spec, origin, ends, np.zeros(spec.shape, np.int32), count=False)
