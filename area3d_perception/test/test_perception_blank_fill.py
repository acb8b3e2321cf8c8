"""Blank surfaces: a plane through the reliable matches around a blank region, and only where the
whole ring around it agrees on one."""

from __future__ import annotations

import numpy as np
import pytest

from area3d_msgs_py.errors import InputError
from area3d_perception.blank_fill import fill_blank_planes
from area3d_perception.stereo import StereoMatcher, StereoParams, texture_factor

from .test_perception_stereo import BASELINE, FX, H, W, _pair, _texture

SHAPE = (120, 160)


def _maps(plane=(0.02, -0.01, 20.0), hole=(40, 80, 50, 110)):
    """Disparity of a plane over the image, textured but for a blank rectangle `hole` (v0, v1,
    u0, u1) whose matches are garbage or missing; the left-right check passed everywhere."""
    v, u = np.mgrid[: SHAPE[0], : SHAPE[1]].astype(np.float64)
    truth = (plane[0] * u + plane[1] * v + plane[2]).astype(np.float32)
    disparity = truth.copy()
    texture = np.full(SHAPE, 0.9, np.float32)
    v0, v1, u0, u1 = hole
    texture[v0:v1, u0:u1] = 0.0
    rng = np.random.default_rng(3)
    disparity[v0:v1, u0:u1] = rng.uniform(5, 40, (v1 - v0, u1 - u0)).astype(np.float32)
    disparity[v0 : v0 + 10, u0:u1] = np.nan  # and no match on part of it
    return truth, disparity, np.zeros(SHAPE, np.float32), texture


def _images():
    """A blank (flat grey) pair: any plane looks right in it; the plane checks are the ring's."""
    grey = np.full(SHAPE, 128, np.uint8)
    return grey, grey


def test_a_blank_hole_in_a_plane_takes_the_plane():
    truth, disparity, diff, texture = _maps()
    out, support, blank = fill_blank_planes(disparity, diff, texture, texture, *_images(), 0.1, 300)
    hole, filled = texture < 0.1, support > 0
    assert np.array_equal(filled, hole)  # every pixel of the hole, nothing else
    assert np.array_equal(blank, hole)
    assert np.abs(out[hole] - truth[hole]).max() < 1e-3
    assert np.all(support[hole] > 0.99)
    assert np.array_equal(out[~hole], disparity[~hole])  # the matched pixels stay as they were
    again, _, _ = fill_blank_planes(disparity, diff, texture, texture, *_images(), 0.1, 300)
    assert np.array_equal(out, again, equal_nan=True)  # seeded


def test_a_regions_plane_does_not_depend_on_the_other_regions_of_the_frame():
    """Each region's RANSAC draws from its own seeded generator: a second blank region fitted
    before it (or one no longer fitted, as an open one) leaves its plane bit for bit the same."""
    truth, disparity, diff, texture = _maps(hole=(60, 100, 90, 150))
    noise = np.random.default_rng(5).normal(0.0, 0.2, SHAPE).astype(np.float32)
    disparity = disparity + noise * (texture > 0.1)  # a noisy ring: the draws decide the plane
    alone, _, _ = fill_blank_planes(disparity, diff, texture, texture, *_images(), 0.1, 300)
    first = texture.copy()
    first[10:50, 40:90] = 0.0  # a region labelled (and fitted) before the hole
    both, support, _ = fill_blank_planes(disparity, diff, first, first, *_images(), 0.1, 300)
    assert support[10:50, 40:90].all() and support[60:100, 90:150].all()
    assert np.array_equal(both[60:100, 90:150], alone[60:100, 90:150])


def test_a_ring_on_two_surfaces_fills_nothing():
    # a step through the middle: a plane tilted across it agrees with 63 % of the ring
    truth, disparity, diff, texture = _maps()
    disparity[:, 80:] += 3.0  # a step through the middle of the hole: two surfaces around it
    disparity[texture < 0.1] = np.nan
    out, support, _ = fill_blank_planes(disparity, diff, texture, texture, *_images(), 0.1, 300)
    assert not support.any()
    assert np.array_equal(out, disparity, equal_nan=True)


def test_a_blank_panel_before_a_farther_surface_takes_its_plane_from_its_own_edge():
    """A blank panel seen against something farther: the ring around its blank middle holds the
    panel's own textured edge (3 px on three sides, 2 px on the fourth here) and, beyond it, the
    farther surface. Under 70 % of the ring lies on the panel (a 4 px ring over a 3 px edge gives
    at most about 74 %), yet more than a plane tilted across two surfaces reaches (63 %, the test
    below): the panel's plane is kept."""
    truth, disparity, diff, texture = _maps()
    v0, v1, u0, u1 = 40, 80, 50, 110
    panel = np.zeros(SHAPE, bool)
    panel[v0 - 3 : v1 + 3, u0 - 2 : u1 + 3] = True
    disparity[~panel] = truth[~panel] - 6.0  # the farther surface around the panel
    hole = texture < 0.1
    ring = np.zeros(SHAPE, bool)
    ring[v0 - 4 : v1 + 4, u0 - 4 : u1 + 4] = True
    ring &= ~hole
    assert 0.65 < panel[ring].mean() < 0.7  # the share of the ring on the panel
    out, support, _ = fill_blank_planes(disparity, diff, texture, texture, *_images(), 0.1, 300)
    assert np.array_equal(support > 0, hole)
    assert np.abs(out[hole] - truth[hole]).max() < 1e-3  # the panel's plane, not the far one
    assert np.all((support[hole] > 0.65) & (support[hole] < 0.7))


def test_a_refused_region_keeps_the_matchers_values_or_none_of_them():
    """The garbage a matcher spread into a blank region stays (drop_refused False) or is no
    estimate (True); the textured pixels around it are the matcher's either way."""
    truth, disparity, diff, texture = _maps()
    disparity[:, 80:] += 3.0  # two surfaces around the hole: no plane is kept
    hole = texture < 0.1
    assert np.isfinite(disparity[hole]).mean() > 0.7  # the matcher's garbage, mostly
    kept, support, _ = fill_blank_planes(disparity, diff, texture, texture, *_images(), 0.1, 300)
    assert not support.any() and np.array_equal(kept, disparity, equal_nan=True)
    dropped, support, _ = fill_blank_planes(
        disparity, diff, texture, texture, *_images(), 0.1, 300, drop_refused=True
    )
    assert not support.any()
    assert np.isnan(dropped[hole]).all()
    assert np.array_equal(dropped[~hole], disparity[~hole], equal_nan=True)
    # a region too small to be looked at is not dropped: it was never refused
    small, _, _ = fill_blank_planes(
        disparity, diff, texture, texture, *_images(), 0.1, int(hole.sum()) + 1, drop_refused=True
    )
    assert np.array_equal(small, disparity, equal_nan=True)
    # a region that takes its plane is filled as before
    truth, disparity, diff, texture = _maps()
    out, support, _ = fill_blank_planes(
        disparity, diff, texture, texture, *_images(), 0.1, 300, drop_refused=True
    )
    assert np.array_equal(support > 0, texture < 0.1)
    assert np.abs(out[texture < 0.1] - truth[texture < 0.1]).max() < 1e-3


def test_a_blank_region_reaching_the_images_top_and_a_side_is_no_estimate():
    """The sky over a horizon: a blank region reaching the image's top and one side has a ring
    on two sides at most; whatever plane that ring agrees on (a pole's edge beside it) is an
    extrapolation, and the matcher's values there are no estimate. A region reaching the top
    alone, the top and the bottom, or a bottom corner (a floor near the camera) is matched on
    its other sides and still takes its plane."""
    for hole in ((0, 50, 100, 160), (0, 50, 0, 60)):  # the top right and top left corners
        truth, disparity, diff, texture = _maps(hole=hole)
        hole = texture < 0.1
        assert np.isfinite(disparity[hole]).mean() > 0.7  # the matcher's garbage, mostly
        for drop_refused in (False, True):
            out, support, blank = fill_blank_planes(
                disparity, diff, texture, texture, *_images(), 0.1, 300, drop_refused=drop_refused
            )
            assert not support.any()
            assert np.array_equal(blank, hole)  # tried, and refused
            assert np.isnan(out[hole]).all()
            assert np.array_equal(out[~hole], disparity[~hole], equal_nan=True)
    bottom_right = (SHAPE[0] - 50, SHAPE[0], 100, SHAPE[1])
    for hole in ((0, 50, 40, 120), (0, SHAPE[0], 40, 120), bottom_right):
        truth, disparity, diff, texture = _maps(hole=hole)
        out, support, _ = fill_blank_planes(disparity, diff, texture, texture, *_images(), 0.1, 300)
        hole = texture < 0.1
        assert np.array_equal(support > 0, hole)
        assert np.abs(out[hole] - truth[hole]).max() < 1e-3


def test_small_striped_or_untrusted_regions_are_left_alone():
    truth, disparity, diff, texture = _maps()
    disparity[texture < 0.1] = np.nan
    # smaller than the least area
    out, support, _ = fill_blank_planes(
        disparity, diff, texture, texture, *_images(), 0.1, 40 * 60 + 1
    )
    assert not support.any()
    # horizontal stripes: nothing to match along a row, but vertical texture: not blank
    vertical = np.full(SHAPE, 0.9, np.float32)
    out, support, _ = fill_blank_planes(disparity, diff, texture, vertical, *_images(), 0.1, 300)
    assert not support.any()
    # a ring whose matches failed the left-right check gives nothing to fit
    out, support, _ = fill_blank_planes(
        disparity, np.full(SHAPE, 2.0), texture, texture, *_images(), 0.1, 300
    )
    assert not support.any()


def _match(left, right, fill, downscale=1, drop_refused=False, model="matcher", refine=True):
    params = StereoParams(
        num_disparities=32,
        refine=refine,
        blank_fill=fill,
        downscale=downscale,
        confidence_model=model,
        blank_drop_refused=drop_refused,
    )
    m = StereoMatcher(params)
    try:
        return m.match(left, right, FX, BASELINE)
    finally:
        m.close()


def _inside(truth, z, margin_px):
    """(H, W) bool: the pixels of the surface at depth `z`, `margin_px` in from its side edges."""
    mask = np.zeros((H, W), bool)
    mask[20:-20] = np.isclose(truth[20:-20], z, atol=1e-3)
    cols = np.flatnonzero(mask.any(axis=0))
    mask[:, : cols[0] + margin_px] = False
    mask[:, cols[-1] - margin_px + 1 :] = False
    return mask


def test_a_blank_panel_in_a_textured_frame_gets_its_depth_at_low_confidence():
    # a board at 1 m before a textured wall at 1.6 m: a 5 cm textured frame, a flat grey middle
    # (0.1 mm in front of the frame, so the renderer draws it)
    wall, frame, blank = _texture(5, True), _texture(6, True), _texture(0, False)
    surfaces = [(1.6, -5, 5, wall), (1.0, -0.3, 0.3, frame), (0.9999, -0.25, 0.25, blank)]
    left, right, truth = _pair(surfaces)
    panel = _inside(truth, 0.9999, 10)
    plain, filled = _match(left, right, False), _match(left, right, True)
    within = {f: np.mean(np.abs(o.depth[panel] - 1.0) < 0.02) for f, o in ((0, plain), (1, filled))}
    assert within[0] < 0.5  # the matcher alone: streaks of wrong depth or none
    assert within[1] > 0.95
    assert 0 < np.median(filled.confidence[panel]) <= 0.2  # an inference, below a matched view
    # the textured wall is the matcher's own, untouched
    wall_px = np.zeros((H, W), bool)
    wall_px[20:-20, 60 : W // 2 - 200] = True
    assert np.array_equal(plain.depth[wall_px], filled.depth[wall_px], equal_nan=True)


def test_matched_at_half_size_the_planes_tolerance_is_that_of_the_matching_pixels():
    # the ring's disparities carry the noise of half-size matching, doubled in full-size pixels:
    # with the full-size tolerance too few ring pixels agree and half the panel stays wrong.
    # Unrefined, as the matcher gives them; refined on the full-size images, the ring is that
    # much better and the plane holds on almost all the panel
    wall, frame, blank = _texture(5, True), _texture(6, True), _texture(0, False)
    surfaces = [(1.6, -5, 5, wall), (1.0, -0.3, 0.3, frame), (0.9999, -0.25, 0.25, blank)]
    left, right, truth = _pair(surfaces)
    panel = _inside(truth, 0.9999, 10)
    plain = _match(left, right, False, 2, refine=False)
    filled = _match(left, right, True, 2, refine=False)
    refined = _match(left, right, True, 2)
    within = [np.mean(np.abs(o.depth[panel] - 1.0) < 0.02) for o in (plain, filled, refined)]
    assert within[0] < 0.3
    assert within[1] > 0.55  # 0.49 with the tolerance in full-size pixels
    assert within[2] > 0.9  # measured 0.95
    assert np.isfinite(filled.depth[panel]).mean() > 0.99


def test_a_blank_board_with_only_the_wall_around_it_is_not_moved_onto_the_wall():
    # the board's edges carry no texture of its own: every reliable match around it is the
    # wall's, and the wall's plane would carve free space through the board; the check of the
    # board's edge through that plane in the right image refuses it. With blank_drop_refused the
    # board has no estimate: what the matcher spread over it is mostly wrong, and carves through it
    wall, blank = _texture(5, True), _texture(0, False)
    left, right, truth = _pair([(1.6, -5, 5, wall), (1.0, -0.3, 0.3, blank)])
    board = _inside(truth, 1.0, 10)
    plain = _match(left, right, False)
    kept = _match(left, right, True)  # the default
    assert np.array_equal(plain.depth[board], kept.depth[board], equal_nan=True)
    assert np.isfinite(plain.depth[board]).mean() > 0.5  # the matcher's values ...
    assert np.mean(np.abs(plain.depth[board] - 1.0) < 0.02) < 0.5  # ... mostly wrong
    dropped = _match(left, right, True, drop_refused=True)
    assert np.isfinite(dropped.depth[board]).mean() < 0.01  # pixels by its edge are not blank
    none = np.isnan(dropped.depth) & board
    assert (dropped.confidence[none] == 0).all() and (dropped.weight[none] == 0).all()
    wall_px = np.zeros((H, W), bool)
    wall_px[20:-20, 60 : W // 2 - 200] = True  # the wall is the matcher's own, untouched
    assert np.array_equal(plain.depth[wall_px], dropped.depth[wall_px], equal_nan=True)
    # the values kept are no measurement: confidence 0 for the planner with either model, the
    # calibrated one too (a smooth spread over a blank board looks like a good match to it)
    for model in ("matcher", "calibrated"):
        out = _match(left, right, True, model=model)
        assert np.array_equal(out.depth[board], kept.depth[board], equal_nan=True)
        assert (out.confidence[board & ~_near_texture(left)] == 0).all(), model
    unfilled = _match(left, right, False, model="calibrated")
    assert unfilled.confidence[board & np.isfinite(unfilled.depth)].mean() > 0.3


def _near_texture(grey: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose texture factor is not blank (the board's edge)."""
    p = StereoParams()
    g = grey if grey.ndim == 2 else grey[..., 0]
    across = texture_factor(g, p.texture_window_px, p.texture_ref)
    along = texture_factor(g.T, p.texture_window_px, p.texture_ref).T
    return (across >= p.blank_texture) | (along >= p.blank_texture)


def test_bad_fill_parameters_are_refused_naming_them():
    with pytest.raises(InputError, match=r"^stereo\.blank_texture: got 1\.5"):
        StereoMatcher(StereoParams(blank_texture=1.5))
    with pytest.raises(InputError, match=r"^stereo\.blank_min_area_px: got 0"):
        StereoMatcher(StereoParams(blank_min_area_px=0))
    with pytest.raises(InputError, match=r"^stereo\.blank_fill_confidence: got -0\.1"):
        StereoMatcher(StereoParams(blank_fill_confidence=-0.1))
